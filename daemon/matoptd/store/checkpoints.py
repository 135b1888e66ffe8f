"""Checkpoints: one file per job (``checkpoints/{id}.npz``, what the engine's ``checkpoint``
returned), replaced in place, atomically: a crash or a full disk while writing leaves the
previous one."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from .disk import Disk


class Checkpoints:
    def __init__(self, root: Path, disk: Disk) -> None:
        self.root, self.disk = root, disk
        self.root.mkdir(parents=True, exist_ok=True)

    def path(self, job: str) -> Path:
        return self.root / f"{job.removeprefix('jobs/')}.npz"

    def write(self, job: str, data: bytes) -> None:
        tmp = None
        try:
            with self.disk.writing():
                fd, tmp = tempfile.mkstemp(dir=self.root, prefix=".write-")
                with os.fdopen(fd, "wb") as f:
                    f.write(data)
                os.replace(tmp, self.path(job))
        except BaseException:
            if tmp:
                Path(tmp).unlink(missing_ok=True)
            raise

    def read(self, job: str) -> bytes | None:
        try:
            return self.path(job).read_bytes()
        except FileNotFoundError:
            return None

    def exists(self, job: str) -> bool:
        return self.path(job).exists()

    def size(self, job: str) -> int:
        """Bytes of the job's checkpoint (0: none)."""
        try:
            return self.path(job).stat().st_size
        except FileNotFoundError:
            return 0

    def delete(self, job: str) -> None:
        self.path(job).unlink(missing_ok=True)

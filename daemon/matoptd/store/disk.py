"""The data directory's disk: a write that finds it full becomes ``DiskFull`` (handlers answer
RESOURCE_EXHAUSTED, lanes hold their jobs), and the daemon remembers since when, until enough
space is free again to go on."""

from __future__ import annotations

import contextlib
import errno
import shutil
import time
from pathlib import Path
from typing import Iterator

from ..errors import DiskFull

FREE_TO_RESUME = 64 << 20  # after the disk filled up, writes go on once this much is free


def is_full(exc: BaseException) -> bool:
    return isinstance(exc, DiskFull) or (isinstance(exc, OSError)
                                         and exc.errno in (errno.ENOSPC, errno.EDQUOT))


class Disk:
    def __init__(self, root: Path) -> None:
        self.root = root
        self.full_since: float | None = None  # when a write last failed for want of space

    def note_full(self) -> None:
        if self.full_since is None:
            self.full_since = time.monotonic()

    def space_back(self) -> bool:
        """Whether writes can go on: true unless the disk filled up and is still short."""
        if self.full_since is not None and shutil.disk_usage(self.root).free >= FREE_TO_RESUME:
            self.full_since = None
        return self.full_since is None

    @contextlib.contextmanager
    def writing(self) -> Iterator[None]:
        """A file write: out of space, it raises DiskFull and notes it."""
        try:
            yield
        except OSError as exc:
            if is_full(exc):
                self.note_full()
                raise DiskFull() from None
            raise

"""The data directory's disk: a write that finds it full becomes ``DiskFull`` (handlers answer
RESOURCE_EXHAUSTED, lanes hold their jobs), and the daemon remembers since when, until enough
space is free again to go on."""

from __future__ import annotations

import contextlib
import errno
import shutil
import time
from pathlib import Path
from typing import Callable, Iterator, NamedTuple

from ..errors import DiskFull

# After the disk filled up, writes go on once the held work's next writes fit, with a margin
# of 1% of the disk, at least MIN_MARGIN (SQLite's records and journal), at most MAX_MARGIN.
MIN_MARGIN = 1 << 20
MAX_MARGIN = 64 << 20


def free_to_resume(total: int, held: int) -> int:
    """The free bytes that let writes go on after the disk filled up: ``held``, what the held
    jobs write next (a checkpoint is written beside the one it replaces, so as much as their
    checkpoints take now), and a margin relative to the disk (``total`` bytes), so that a large
    disk does not fill up again at once and a small one is not asked for more than it has."""
    return held + min(MAX_MARGIN, max(MIN_MARGIN, total // 100))


class Usage(NamedTuple):
    """What ``shutil.disk_usage`` reads, in bytes."""

    total: int
    used: int
    free: int


def is_full(exc: BaseException) -> bool:
    return isinstance(exc, DiskFull) or (isinstance(exc, OSError)
                                         and exc.errno in (errno.ENOSPC, errno.EDQUOT))


class Disk:
    def __init__(self, root: Path, usage: Callable[[Path], Usage] = shutil.disk_usage
                 ) -> None:
        self.root, self.usage = root, usage
        self.full_since: float | None = None  # when a write last failed for want of space

    def note_full(self) -> None:
        if self.full_since is None:
            self.full_since = time.monotonic()

    def space_back(self, held: int = 0) -> bool:
        """Whether writes can go on: true unless the disk filled up and is still short of
        what the held work (``held`` bytes) needs (``free_to_resume``)."""
        if self.full_since is not None:
            usage = self.usage(self.root)
            if usage.free >= free_to_resume(usage.total, held):
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

"""After the disk filled up, writes go on once the free space covers what the held work needs
next, with a margin relative to the disk: a small disk resumes as soon as it can, a large one
keeps room. Simulated free-space readings; the lanes with the fake engine and a memory store
(``fakes.py``); a real daemon on a small tmpfs is in test_disk_full.py."""

from __future__ import annotations

from pathlib import Path

from matoptd.errors import DiskFull
from matoptd.records import Phase
from matoptd.scheduling.monitor import Monitor
from matoptd.store.disk import Disk, Usage, free_to_resume

from fakes import job
from test_lanes import Daemon

MiB, GiB = 1 << 20, 1 << 30


def test_the_margin_follows_the_disk_and_the_held_work_adds_to_it():
    assert free_to_resume(40 * MiB, 0) == 1 * MiB            # a small disk: the least margin
    assert free_to_resume(40 * MiB, 3 * MiB) == 4 * MiB      # ...plus the held checkpoints
    assert free_to_resume(2 * GiB, 0) == 2 * GiB // 100      # 1% of the disk
    assert free_to_resume(4000 * GiB, 5 * MiB) == 69 * MiB   # at most 64 MiB of margin


class SimulatedDisk(Disk):
    """``store.disk.Disk`` reading a simulated free space; the memory store's writes fail
    (as a full disk's) while less than 64 KiB is free."""

    def __init__(self, total: int) -> None:
        self.total, self.free = total, total
        super().__init__(Path("/nowhere"),
                         lambda root: Usage(self.total, self.total - self.free, self.free))

    def write(self) -> None:
        if self.free < 64 << 10:
            self.note_full()
            raise DiskFull()


def test_space_back_once_free_covers_the_held_work():
    disk = SimulatedDisk(200 * GiB)
    disk.note_full()
    disk.free = 50 * MiB
    assert not disk.space_back(held=20 * MiB)  # 64 MiB of margin and 20 MiB of checkpoints
    disk.free = 85 * MiB
    assert disk.space_back(held=20 * MiB) and disk.full_since is None


def test_a_small_disk_resumes_its_held_job_as_soon_as_space_returns():
    """On a 40 MiB disk 64 MiB is never free: a fixed threshold would hold the job forever."""
    d = Daemon()
    disk = d.store.disk = SimulatedDisk(40 * MiB)
    d.control.create(job("a", iterations=40), None)
    for _ in range(3):
        d.lane.turn()
    disk.free = 0
    for _ in range(3):
        d.lane.turn()
    assert d.state.scheduler.held and not d.lanes.serving
    monitor = Monitor(d.state, d.recovery, lambda: True)
    disk.free = MiB // 2  # a little freed: not yet what a margin of 1 MiB asks
    monitor.check()
    assert d.state.scheduler.held and not d.lanes.serving
    disk.free = 2 * MiB  # an administrator freed 2 MiB of the 40
    monitor.check()
    assert not d.state.scheduler.held and d.lanes.serving
    d.run()
    done = d.store.get_job("jobs/a")
    assert done.phase is Phase.SUCCEEDED and d.history("jobs/a") == list(range(40))

"""A watcher's queue of job events: bounded, so that a stalled client cannot grow the daemon
without limit, and lossy only where a slow watcher can afford it."""

from __future__ import annotations

import asyncio

from matopt_api.v1 import matopt_pb2 as pb


class EventQueue(asyncio.Queue):
    """When full, the oldest iteration event gives way to the new event (of either kind): a
    slow watcher misses iteration records, never a state change. A queue of job events only
    drops its oldest; each carries the whole job, so the newer ones hold what it said."""

    def offer(self, event: pb.JobEvent) -> None:
        if self.full():
            queued = self._queue  # asyncio.Queue's own deque, as its subclasses use it
            oldest = next((i for i, e in enumerate(queued) if not e.HasField("job")), 0)
            del queued[oldest]
        self.put_nowait(event)

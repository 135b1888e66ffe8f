"""What watchers of a job are told: the job's record after each change, and each iteration's
record, handed from the lanes' threads to the watchers' event loops.

An event is plain data: a ``JobRecord`` snapshot or an ``engine_api.IterationRecord``; the
API's WatchJob turns it into a message. A watcher's queue is bounded, so that a stalled client
cannot grow the daemon without limit, and lossy only where a slow watcher can afford it.
"""

from __future__ import annotations

import asyncio
import collections
import threading
from typing import Union

from ..engine_api import IterationRecord
from ..records import JobRecord

Event = Union[JobRecord, IterationRecord]
WATCH_QUEUE = 10000


class EventQueue(asyncio.Queue):
    """When full, the oldest iteration event gives way to the new event (of either kind): a
    slow watcher misses iteration records, never a state change. A queue of job events only
    drops its oldest; each carries the whole job, so the newer ones hold what it said."""

    def offer(self, event: Event) -> None:
        if self.full():
            queued = self._queue  # asyncio.Queue's own deque, as its subclasses use it
            oldest = next((i for i, e in enumerate(queued) if not isinstance(e, JobRecord)), 0)
            del queued[oldest]
        self.put_nowait(event)


class Events:
    """The watchers of each job: queues on the event loops they were made on."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._watchers: dict[str, list[tuple[asyncio.AbstractEventLoop, EventQueue]]] = \
            collections.defaultdict(list)

    def subscribe(self, name: str) -> EventQueue:
        q = EventQueue(maxsize=WATCH_QUEUE)
        with self._lock:
            self._watchers[name].append((asyncio.get_running_loop(), q))
        return q

    def unsubscribe(self, name: str, q: EventQueue) -> None:
        with self._lock:
            left = [(lp, x) for lp, x in self._watchers.get(name, []) if x is not q]
            if left:
                self._watchers[name] = left
            else:
                self._watchers.pop(name, None)

    def publish(self, name: str, events: list[Event]) -> None:
        """Hands events to every watcher of the job: one wake-up per event loop, not per
        watcher. Records are handed as they are: publish snapshots."""
        by_loop: dict[asyncio.AbstractEventLoop, list[EventQueue]] = {}
        with self._lock:
            for loop, q in self._watchers.get(name, ()):
                by_loop.setdefault(loop, []).append(q)
        for loop, queues in by_loop.items():
            try:
                loop.call_soon_threadsafe(_offer, queues, events)
            except RuntimeError:  # that loop is closed: its watchers are gone
                pass


def _offer(queues: list[EventQueue], events: list[Event]) -> None:
    for q in queues:
        for event in events:
            q.offer(event)

"""What the handlers reach, in one object: the store, the lanes, job control, the watchers and
the admission limits."""

from __future__ import annotations

from dataclasses import dataclass, field

from ..scheduling.control import JobControl
from ..scheduling.events import Events
from ..scheduling.lanes import Lanes
from ..store.store import Store
from . import admission


@dataclass
class Backend:
    """The store (status calls are served from it), the lanes (scene tasks, the workers), job
    control and the jobs' watchers."""

    store: Store
    lanes: Lanes
    control: JobControl
    events: Events
    limits: admission.Limits = admission.Limits()
    tasks: admission.TaskSlots = field(init=False)  # scene requests in flight, per user

    def __post_init__(self) -> None:
        self.tasks = admission.TaskSlots(self.limits)

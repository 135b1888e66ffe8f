"""A watcher's event queue when the watcher falls behind: iteration records give way, state
changes never do. Pure logic, no daemon."""

from __future__ import annotations

from dataclasses import replace

from matoptd.engine_api import IterationRecord
from matoptd.records import JobRecord, Phase
from matoptd.scheduling.events import EventQueue
from matoptd.settings import JobSettings, SceneInput

JOB = JobRecord("jobs/a", "alice", "scenes/s", JobSettings(SceneInput("", "", {}, {}, ""), [], []))


def _iteration(i: int) -> IterationRecord:
    return IterationRecord(i, 0.0, 0.0, {})


def _state(phase: Phase) -> JobRecord:
    return replace(JOB, phase=phase)


def _drain(q: EventQueue) -> list[str]:
    out = []
    while not q.empty():
        e = q.get_nowait()
        out.append(e.phase.name if isinstance(e, JobRecord) else f"iteration {e.iteration}")
    return out


def test_a_full_queue_drops_the_oldest_iteration_never_a_state_change():
    q = EventQueue(maxsize=3)
    for e in (_iteration(0), _state(Phase.PAUSED), _iteration(1), _state(Phase.RUNNING),
              _iteration(2), _state(Phase.SUCCEEDED)):
        q.offer(e)
    assert _drain(q) == ["PAUSED", "RUNNING", "SUCCEEDED"]


def test_the_newest_iteration_is_kept_over_the_oldest():
    q = EventQueue(maxsize=2)
    for i in range(5):
        q.offer(_iteration(i))
    assert _drain(q) == ["iteration 3", "iteration 4"]


def test_a_queue_of_states_only_drops_the_oldest_state():
    # Each job event carries the whole job: the newer ones hold what the dropped one said.
    q = EventQueue(maxsize=2)
    for e in (_state(Phase.QUEUED), _state(Phase.RUNNING), _iteration(7),
              _state(Phase.CANCELLED)):
        q.offer(e)
    # QUEUED gave way to iteration 7 (nothing else could), which gave way to CANCELLED.
    assert _drain(q) == ["RUNNING", "CANCELLED"]

"""A watcher's event queue when the watcher falls behind: iteration records give way, state
changes never do. Pure logic, no daemon."""

from __future__ import annotations

from matopt_api.v1 import matopt_pb2 as pb
from matoptd.scheduling.events import EventQueue


def _iteration(i: int) -> pb.JobEvent:
    return pb.JobEvent(iteration=pb.IterationRecord(iteration=i))


def _state(state: int) -> pb.JobEvent:
    return pb.JobEvent(job=pb.Job(name="jobs/a", state=state))


def _drain(q: EventQueue) -> list[str]:
    out = []
    while not q.empty():
        e = q.get_nowait()
        out.append(pb.JobState.Name(e.job.state) if e.HasField("job") else
                   f"iteration {e.iteration.iteration}")
    return out


def test_a_full_queue_drops_the_oldest_iteration_never_a_state_change():
    q = EventQueue(maxsize=3)
    for e in (_iteration(0), _state(pb.JOB_STATE_PAUSED), _iteration(1),
              _state(pb.JOB_STATE_RUNNING), _iteration(2), _state(pb.JOB_STATE_SUCCEEDED)):
        q.offer(e)
    assert _drain(q) == ["JOB_STATE_PAUSED", "JOB_STATE_RUNNING", "JOB_STATE_SUCCEEDED"]


def test_the_newest_iteration_is_kept_over_the_oldest():
    q = EventQueue(maxsize=2)
    for i in range(5):
        q.offer(_iteration(i))
    assert _drain(q) == ["iteration 3", "iteration 4"]


def test_a_queue_of_states_only_drops_the_oldest_state():
    # Each job event carries the whole job: the newer ones hold what the dropped one said.
    q = EventQueue(maxsize=2)
    for e in (_state(pb.JOB_STATE_QUEUED), _state(pb.JOB_STATE_RUNNING), _iteration(7),
              _state(pb.JOB_STATE_CANCELLED)):
        q.offer(e)
    # QUEUED gave way to iteration 7 (nothing else could), which gave way to CANCELLED.
    assert _drain(q) == ["JOB_STATE_RUNNING", "JOB_STATE_CANCELLED"]

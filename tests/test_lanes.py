"""The lanes, recovery and job control without a daemon: a fake engine that only counts
iterations, fake workers in this thread, a store in memory and a fake clock (``fakes.py``).
What a user would see is checked on the records and the history the store keeps."""

from __future__ import annotations

import pytest

from matoptd.records import Phase
from matoptd.scheduling.control import JobControl
from matoptd.scheduling.events import Events
from matoptd.scheduling.lanes import Lane, Lanes
from matoptd.scheduling.monitor import CANCEL_GRACE_S, SHUTDOWN_GRACE_S, Monitor
from matoptd.scheduling.recovery import Recovery
from matoptd.scheduling.scheduler import Scheduler
from matoptd.scheduling.state import State

from fakes import ESTIMATE_PARTS, KEY, Clock, FakeEngine, FakeWorker, MemoryStore, job

WATCHDOG = 120.0


class Daemon:
    """One worker's lane with job control and recovery over a memory store."""

    def __init__(self, store: MemoryStore | None = None) -> None:
        self.clock = Clock()
        self.store = store or MemoryStore()
        self.state = State(self.store, Scheduler(clock=self.clock.monotonic), Events(),
                           self.clock)
        self.recovery = Recovery(self.state, WATCHDOG)
        self.recovery.recover()
        self.engine = FakeEngine(self.clock)
        self.worker = FakeWorker("workers/0", self.engine)
        self.lanes = Lanes(self.state, [self.worker], WATCHDOG, self.recovery)
        self.lane = Lane(self.state, self.worker, WATCHDOG, self.recovery)
        assert self.lane.start_worker() == ""
        self.control = JobControl(self.state, self.recovery)
        self.actions: list[tuple[str, str]] = []

    def run(self, turns: int = 10_000) -> None:
        """Turns of the lane until it has nothing to do."""
        for _ in range(turns):
            action = self.lane.turn()
            if action is None:
                return
            self.actions.append((action.kind, action.job))
        raise AssertionError("the lane never ran out of work")

    def history(self, name: str) -> list[int]:
        return [r.iteration for r in self.store.history(name)]


def test_a_job_runs_through_its_lane_to_its_results():
    d = Daemon()
    d.control.create(job("a", iterations=30, sensors=2), None)
    d.run()
    done = d.store.get_job("jobs/a")
    assert (done.phase, done.iteration, done.stop_reason) == (Phase.SUCCEEDED, 30, "iterations")
    assert d.history("jobs/a") == list(range(30))
    assert "stopped after all 30 iterations" in done.notes
    best = d.store.results[("jobs/a", "best")]
    assert [i.sensor for i in best.images] == [0, 1]  # one end-phase action per sensor
    # one end-phase action per sensor, then the standard errors' pieces, then the finish
    assert [k for k, _ in d.actions if k in ("results", "estimate", "finish")] == (
        ["results"] * 2 + ["estimate"] * ESTIMATE_PARTS + ["finish"])
    assert done.ending is None and "jobs/a" not in d.state.scheduler.jobs


def test_a_worker_lost_mid_iteration_costs_the_job_only_what_ran_since_its_checkpoint():
    d = Daemon()
    d.control.create(job("a", iterations=60), None)

    def die_at_iteration_35(method, args):
        if method == "step" and d.engine.runs["jobs/a"].iteration >= 35 and not d.worker.restarts:
            d.worker.die()
    d.worker.before = die_at_iteration_35
    d.run()
    done = d.store.get_job("jobs/a")
    assert done.phase is Phase.SUCCEEDED, done.error
    assert d.history("jobs/a") == list(range(60))  # each iteration there, once
    checkpoint = d.engine.started[-1]
    assert d.engine.started[0] == ("jobs/a", 0) and 20 <= checkpoint[1] <= 35, d.engine.started
    assert done.resumed_from == f"checkpoint at iteration {checkpoint[1]}"
    assert any(n.startswith("the renderer process died with SIGSEGV during iteration ")
               and n.endswith("the job goes on from its last checkpoint on a fresh worker")
               for n in done.notes), done.notes


def test_a_worker_lost_in_the_end_phase_still_gives_the_results_of_the_last_iteration():
    d = Daemon()
    d.control.create(job("a", iterations=35, sensors=2), None)

    def die_rendering_results(method, args):
        if method == "result_images" and not d.worker.restarts:
            d.worker.die()
    d.worker.before = die_rendering_results
    d.run()
    done = d.store.get_job("jobs/a")
    assert done.phase is Phase.SUCCEEDED and done.iteration == 35
    assert d.engine.started[-1] == ("jobs/a", 35)  # loaded again as its iterations left it
    assert d.store.results[("jobs/a", "last")].iteration == 34
    assert [i.sensor for i in d.store.results[("jobs/a", "last")].images] == [0, 1]


def test_a_job_that_takes_its_worker_down_twice_fails_and_says_how():
    d = Daemon()
    d.control.create(job("bad", iterations=60), None)
    d.control.create(job("good", owner="bob", iterations=20), None)

    def bad_job_kills(method, args):
        if method == "step" and args[0] == "jobs/bad" and d.engine.runs["jobs/bad"].iteration >= 5:
            d.worker.die()
    d.worker.before = bad_job_kills
    d.run()
    bad, good = d.store.get_job("jobs/bad"), d.store.get_job("jobs/good")
    assert bad.phase is Phase.FAILED and bad.stop_reason == "failed"
    assert bad.error.startswith("the renderer process died with SIGSEGV during iteration ")
    assert ", then died with SIGSEGV during iteration " in bad.error
    assert bad.error.endswith("a job that takes its worker down twice is not tried again "
                              "(other jobs were not affected)")
    assert good.phase is Phase.SUCCEEDED and d.history("jobs/good") == list(range(20))


def test_a_pause_that_races_the_last_iteration_lets_the_job_finish():
    """The pause arrives while the step that ends the job is in flight: the job ends
    SUCCEEDED with its results; it is not parked, nor left PAUSED."""
    d = Daemon()
    d.control.create(job("a", iterations=30), None)
    paused = []

    def pause_during_the_last_step(method, args):
        run = d.engine.runs.get("jobs/a")
        if method == "step" and run and run.iteration + args[1] >= 30 and not paused:
            paused.append(d.control.pause("alice", "jobs/a"))
    d.worker.before = pause_during_the_last_step
    d.run()
    assert paused[0].phase is Phase.PAUSING  # what the pause answered: it would park...
    done = d.store.get_job("jobs/a")
    assert done.phase is Phase.SUCCEEDED and done.iteration == 30  # ...but the job ended
    assert "park" not in [k for k, _ in d.actions]
    assert ("jobs/a", "last") in d.store.results


def test_a_pause_at_an_iteration_boundary_parks_and_resume_continues_from_there():
    d = Daemon()
    d.control.create(job("a", iterations=40), None)
    for _ in range(4):
        d.lane.turn()
    assert d.control.pause("alice", "jobs/a").phase is Phase.PAUSING  # loaded: it parks
    d.run()
    paused = d.store.get_job("jobs/a")
    assert paused.phase is Phase.PAUSED and paused.checkpoint == paused.iteration
    d.control.resume("alice", "jobs/a")
    d.run()
    done = d.store.get_job("jobs/a")
    assert done.phase is Phase.SUCCEEDED
    assert done.resumed_from == f"checkpoint at iteration {paused.iteration}"
    assert d.history("jobs/a") == list(range(40))


def test_a_cancel_kept_waiting_by_a_long_iteration_stops_the_worker():
    d = Daemon()
    d.control.create(job("a", iterations=1000), None)
    monitor = Monitor(d.state, d.recovery, lambda: True)

    def cancel_then_wait(method, args):
        if method == "step" and d.engine.runs["jobs/a"].iteration >= 10:
            d.control.cancel("alice", "jobs/a")
            d.clock.t += CANCEL_GRACE_S + 1  # the iteration goes on and on...
            monitor.check()                  # ...until the monitor stops its worker
            d.worker.before = None
    d.worker.before = cancel_then_wait
    d.run()
    done = d.store.get_job("jobs/a")
    assert (done.phase, done.stop_reason) == (Phase.CANCELLED, "cancelled")
    assert any(n.startswith("cancelled during a long iteration: its renderer process was "
                            "stopped") for n in done.notes)
    assert d.worker.restarts == 1 and d.worker.state == "idle"  # a fresh process took over
    # What it finished is kept: the last finished iteration is its LAST and (the loss only
    # fell) its BEST, with the values that iteration reported.
    finished = done.iteration - 1
    assert finished >= 9
    for which in ("last", "best"):
        kept = d.store.results[("jobs/a", which)]
        assert kept.iteration == finished
        assert kept.values[KEY].inline == pytest.approx([finished / 100] * 3)
        assert kept.initial[KEY].inline == pytest.approx([0.0] * 3)
        assert kept.loss == pytest.approx(1 / (finished + 1))


def test_a_cancel_inside_the_first_iteration_leaves_no_results():
    d = Daemon()
    d.control.create(job("a", iterations=1000), None)
    monitor = Monitor(d.state, d.recovery, lambda: True)

    def cancel_then_wait(method, args):
        if method == "step":
            d.control.cancel("alice", "jobs/a")
            d.clock.t += CANCEL_GRACE_S + 1
            monitor.check()
            d.worker.before = None
    d.worker.before = cancel_then_wait
    d.run()
    done = d.store.get_job("jobs/a")
    assert done.phase is Phase.CANCELLED and done.iteration == 0
    assert not [k for k in d.store.results if k[0] == "jobs/a"]
    assert any("so the job has no results" in n for n in done.notes)


def test_a_shutdown_cuts_off_an_iteration_only_past_its_grace():
    d = Daemon()
    d.control.create(job("a", iterations=1000), None)
    monitor = Monitor(d.state, d.recovery, lambda: True)
    for _ in range(5):
        d.lane.turn()
    kills: list[tuple[float, str]] = []
    kill = d.worker.kill
    d.worker.kill = lambda reason, cause: (kills.append((d.clock.t, reason)), kill(reason, cause))
    with d.state.lock:
        d.state.stop_asked = d.clock.monotonic()
    asked = d.clock.t

    def long_step(method, args):
        if method == "step":
            while not kills and d.clock.t < asked + 60:  # the monitor looks every second
                d.clock.t += 1.0
                monitor.check()
    d.worker.before = long_step
    d.lane.turn()
    assert len(kills) == 1
    when, reason = kills[0]
    assert SHUTDOWN_GRACE_S < when - asked <= SHUTDOWN_GRACE_S + 1
    assert reason == "was stopped: the daemon shut down during a long iteration"
    d.recovery.interrupt_all("the daemon was shut down")
    record = d.store.get_job("jobs/a")
    assert record.phase is Phase.INTERRUPTED
    assert record.stop_reason.startswith("the daemon was shut down")


def test_a_cancel_at_an_iteration_boundary_ends_the_job_with_its_results():
    d = Daemon()
    d.control.create(job("a", iterations=1000, sensors=3), None)
    for _ in range(5):
        d.lane.turn()
    cancelling = d.control.cancel("alice", "jobs/a")
    assert cancelling.phase is Phase.CANCELLING
    d.run()
    done = d.store.get_job("jobs/a")
    assert (done.phase, done.stop_reason) == (Phase.CANCELLED, "cancelled")
    assert any(n.startswith(f"cancelled at iteration {done.iteration}") for n in done.notes)
    assert len(d.store.results[("jobs/a", "best")].images) == 3


def test_after_a_restart_running_jobs_are_interrupted_and_resume_from_their_checkpoint():
    store = MemoryStore()
    first = Daemon(store)
    first.control.create(job("a", iterations=50), None)
    first.control.create(job("b", owner="bob", iterations=10), None)
    for _ in range(12):  # a runs past a checkpoint; b waits its turn
        first.lane.turn()
    ran = store.get_job("jobs/a")
    assert ran.phase is Phase.RUNNING and ran.checkpoint and ran.iteration > ran.checkpoint
    # The daemon is killed here: nothing more is recorded. A new one starts on the store.
    second = Daemon(store)
    interrupted = store.get_job("jobs/a")
    assert interrupted.phase is Phase.INTERRUPTED
    assert interrupted.stop_reason == ("the daemon stopped while the job ran; resume continues "
                                       f"from the checkpoint at iteration {ran.checkpoint}")
    assert "jobs/b" in second.state.scheduler.jobs  # a queued job queues again
    second.control.resume("alice", "jobs/a")
    second.run()
    done, other = store.get_job("jobs/a"), store.get_job("jobs/b")
    assert done.phase is Phase.SUCCEEDED and other.phase is Phase.SUCCEEDED
    assert done.resumed_from == f"checkpoint at iteration {ran.checkpoint}"
    assert second.history("jobs/a") == list(range(50))
    assert ("jobs/a", ran.checkpoint) in second.engine.started


def test_a_full_disk_holds_the_job_and_nothing_is_lost():
    d = Daemon()
    d.control.create(job("a", iterations=40), None)
    for _ in range(3):
        d.lane.turn()
    d.store.disk.free = False
    for _ in range(3):
        d.lane.turn()
    assert d.state.scheduler.held and d.lane.turn() is None  # held: nothing starts
    held = d.store.get_job("jobs/a")
    assert held.phase is Phase.RUNNING and not held.error
    d.store.disk.free = True
    Monitor(d.state, d.recovery, lambda: True).check()  # space is back
    d.run()
    done = d.store.get_job("jobs/a")
    assert done.phase is Phase.SUCCEEDED and d.history("jobs/a") == list(range(40))


@pytest.mark.parametrize("phase", [Phase.SUCCEEDED, Phase.FAILED, Phase.CANCELLED])
def test_a_job_that_ended_cannot_be_paused_resumed_or_cancelled(phase):
    d = Daemon()
    record = job("a")
    record.phase = phase
    d.store.add_job(record, None)
    for act, verb in ((d.control.pause, "paused"), (d.control.resume, "resumed")):
        with pytest.raises(Exception) as err:
            act("alice", "jobs/a")
        assert str(err.value) == (f"job 'jobs/a' is {phase.name}: only a "
                                  f"{'queued or running' if verb == 'paused' else 'paused or interrupted'}"
                                  f" job can be {verb}")
    with pytest.raises(Exception) as err:
        d.control.cancel("alice", "jobs/a")
    assert str(err.value) == f"job 'jobs/a' already ended ({phase.name})"


@pytest.mark.parametrize("turn", [0.0, 0.005])
def test_a_niced_server_gets_the_cpu_when_a_client_waits_on_a_job(monkeypatch, turn):
    """Beside CPU workers the server runs niced below them: the lane leaves it the CPU
    (``State.server_turn``) before a job's load (the CreateJob answer) and after its first
    iteration (that event), with the worker idle; at 0 (GPU workers) never."""
    import matoptd.scheduling.lanes as lanes
    d = Daemon()
    d.state.server_turn = turn
    said: list[str] = []
    monkeypatch.setattr(lanes.time, "sleep", lambda s: said.append(f"sleep {s}"))
    d.worker.before = lambda method, args: said.append(method)
    d.control.create(job("a", iterations=5), None)
    d.run()
    steps = said.index("step")
    if turn:
        assert said[said.index("start") - 1] == f"sleep {turn}"
        assert said[steps + 1] == f"sleep {turn}"  # after the first step alone
        assert said.count(f"sleep {turn}") == 2
    else:
        assert not [s for s in said if s.startswith("sleep")]
    assert d.store.get_job("jobs/a").phase is Phase.SUCCEEDED

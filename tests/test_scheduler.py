"""The scheduler as a state machine: fake workers, a fake clock, no daemon, no Mitsuba.

A fake worker "runs" each action the scheduler hands it by advancing the clock by the action's
cost (``COSTS``) and reporting it done, which is what a lane does with a real worker.
"""

from __future__ import annotations

import collections

import pytest

from matoptd.records import JobRecord, Phase
from matoptd.scheduling.scheduler import Action, Scheduler
from matoptd.settings import JobSettings, SceneInput

ITERATION = 0.01                                    # seconds per iteration of every job
COSTS = {"load": 0.2, "evict": 0.05, "park": 0.05, "cancel": 0.0, "results": 0.3,
         "estimate": 0.25, "finish": 0.1, "task": 0.1}
ESTIMATES = 6  # "estimate" actions a job's standard errors take in run(): 1.5 s


class Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


SETTINGS = JobSettings(SceneInput("", "", {}, {}, ""), [], [])


def add(s: Scheduler, name: str, user: str) -> None:
    s.add_job(JobRecord(name, user, "scenes/s", SETTINGS))


def make(workers: int = 1, **kw) -> tuple[Scheduler, Clock]:
    clock = Clock()
    s = Scheduler(clock=clock, **kw)
    for i in range(workers):
        s.add_worker(f"w{i}")
        s.worker_ready(f"w{i}")
    return s, clock


def run(s: Scheduler, clock: Clock, seconds: float, remaining: dict[str, int] | None = None,
        parts: dict[str, int] | None = None, estimates: dict[str, int] | None = None
        ) -> list[Action]:
    """Runs the workers in turn (one action each, lowest clock first) for ``seconds``.
    ``remaining``: iterations left per job; a job ends when they run out. ``parts``: the
    sensors whose result images a cancelled job's end phase renders (as the runner says).
    ``estimates``: "estimate" actions so far per job (its standard errors take ESTIMATES)."""
    done: list[Action] = []
    estimates = collections.Counter() if estimates is None else estimates
    free_at = {w: clock.t for w in s.workers}
    end = clock.t + seconds
    while True:
        w = min(free_at, key=free_at.get)
        if free_at[w] >= end:
            return done
        clock.t = max(clock.t, free_at[w])
        action = s.next(w)
        if action is None:
            free_at[w] = clock.t + 0.05
            continue
        over = False
        if action.kind == "step":
            n = action.n
            if remaining is not None:
                n = min(n, remaining[action.job])
                remaining[action.job] -= n
                over = remaining[action.job] == 0
            clock.t += n * ITERATION
        else:
            clock.t += COSTS[action.kind]
            n = 0
        estimates[action.job] += action.kind == "estimate"
        s.done(action, iterations=n, estimated=estimates[action.job] >= ESTIMATES)
        if over:  # as a lane does when a step reports the job done
            s.end(action.job, Phase.SUCCEEDED, "iterations", 0)
        if action.kind == "cancel":
            s.end(action.job, Phase.CANCELLED, "cancelled", (parts or {}).get(action.job, 0))
        free_at[w] = clock.t
        done.append(action)


def iterations(actions: list[Action]) -> dict[str, int]:
    out: dict[str, int] = collections.Counter()
    for a in actions:
        if a.kind == "step":
            out[a.job] += a.n
    return out


def test_fair_share_is_per_user_not_per_job():
    s, clock = make()
    for i in range(10):
        add(s, f"alice{i}", "alice")
    add(s, "bob0", "bob")
    done = run(s, clock, 120)
    per_user = collections.Counter()
    for job, n in iterations(done).items():
        per_user[job.rstrip("0123456789")] += n
    ratio = per_user["alice"] / per_user["bob"]
    assert 0.8 < ratio < 1.25, per_user  # not 10:1
    # and alice's ten jobs share her half among themselves
    alice = [iterations(done)[f"alice{i}"] for i in range(10)]
    assert min(alice) > 0.5 * max(alice), alice


def test_switching_keeps_most_of_the_device_busy_with_iterations():
    """8 users with 5 jobs each: slices are long against a switch (evict + load), so the
    total iteration rate stays near one job's."""
    s, clock = make()
    for u in range(8):
        for j in range(5):
            add(s, f"u{u}j{j}", f"user{u}")
    seconds = 300
    done = run(s, clock, seconds)
    busy_iterating = sum(iterations(done).values()) * ITERATION
    assert busy_iterating / seconds >= 0.8
    assert len(iterations(done)) == 40  # every job ran


def test_a_new_users_first_iteration_starts_within_a_few_seconds():
    s, clock = make()
    for u in range(8):
        for j in range(5):
            add(s, f"u{u}j{j}", f"user{u}")
    run(s, clock, 600)  # everybody has a long history of use
    add(s, "newcomer", "new")
    arrived = clock.t
    done = run(s, clock, 30)
    first = next(a for a in done if a.job == "newcomer" and a.kind == "step")
    assert first.began - arrived < 3 * s.slice_seconds


def test_a_returning_user_gets_no_saved_up_credit():
    s, clock = make()
    add(s, "a0", "alice")
    add(s, "b0", "bob")
    run(s, clock, 60)
    add(s, "carol0", "carol")  # new: starts at the least busy active user's account
    done = run(s, clock, 60)
    n = iterations(done)
    assert n["carol0"] < 1.5 * min(n["a0"], n["b0"]), n  # a share, not a monopoly


def test_a_job_stays_on_its_worker_and_new_jobs_go_to_the_least_loaded():
    s, clock = make(workers=2)
    add(s, "a", "alice")
    first = s.next("w0")
    assert (first.kind, first.job) == ("load", "a")
    s.done(first)
    add(s, "b", "bob")
    # w0 holds a; b goes to the idle w1, which holds nothing, even if w0 asks first
    assert s.next("w0").kind == "step"
    second = s.next("w1")
    assert (second.kind, second.job) == ("load", "b")
    s.done(second)
    steps = collections.Counter()
    for _ in range(50):
        for w in ("w0", "w1"):
            action = s.next(w)
            if action is not None:
                assert action.kind == "step" or action.kind == "task"
                assert action.job == {"w0": "a", "w1": "b"}[w] or action.job == ""
                steps[action.job] += action.kind == "step"
                clock.t += 0.5
                s.done(action, iterations=action.n)
            busy = s.workers[w].action
            if busy is not None:
                s.done(busy, iterations=busy.n)
    assert steps["a"] > 10 and steps["b"] > 10, steps  # both kept stepping, each on its own


def test_pause_and_cancel_act_at_the_next_iteration_boundary():
    s, clock = make()
    add(s, "a", "alice")
    s.done(s.next("w0"))                           # load
    step = s.next("w0")
    assert s.pause("a") is False                   # busy: it will park at the boundary
    s.done(step, iterations=step.n)
    park = s.next("w0")
    assert (park.kind, park.job) == ("park", "a")
    s.done(park)
    assert s.jobs["a"].phase is Phase.PAUSED and s.next("w0") is None  # paused: no run
    s.resume("a")
    load = s.next("w0")
    assert (load.kind, load.job) == ("load", "a")  # from its checkpoint
    s.done(load)
    step = s.next("w0")
    assert s.cancel("a") is False
    s.done(step, iterations=step.n)
    cancel = s.next("w0")
    assert (cancel.kind, cancel.job) == ("cancel", "a")
    s.done(cancel)
    s.end("a", Phase.CANCELLED, "cancelled", 2)    # two sensors' result images to make
    assert [(a.kind, a.n) for a in (s.next("w0"),)] == [("results", 0)]
    s.done(s.workers["w0"].action)
    assert s.cancel("a") is False                  # a second cancel changes nothing
    results = s.next("w0")
    assert (results.kind, results.n) == ("results", 1)
    s.done(results)
    estimate = s.next("w0")                        # then its standard errors, in pieces
    assert (estimate.kind, estimate.job) == ("estimate", "a")
    s.done(estimate)                               # not done: another piece
    estimate = s.next("w0")
    assert estimate.kind == "estimate"
    s.done(estimate, estimated=True)
    finish = s.next("w0")
    assert finish.kind == "finish"
    s.done(finish)
    assert "a" not in s.jobs


def test_a_cancel_that_arrives_while_the_job_parks_still_ends_it():
    s, clock = make()
    add(s, "a", "alice")
    s.done(s.next("w0"))
    step = s.next("w0")
    s.pause("a")
    s.done(step, iterations=step.n)
    park = s.next("w0")
    assert s.cancel("a") is False                  # busy parking
    s.done(park)
    load = s.next("w0")                            # loaded again, to make its results
    assert (load.kind, load.job) == ("load", "a")
    s.done(load)
    cancel = s.next("w0")
    assert cancel.kind == "cancel"
    s.done(cancel)
    s.end("a", Phase.CANCELLED, "cancelled", 1)    # the paused job's end phase runs too
    results = s.next("w0")
    assert (results.kind, results.job) == ("results", "a")
    s.done(results)
    estimate = s.next("w0")
    assert (estimate.kind, estimate.job) == ("estimate", "a")
    s.done(estimate, estimated=True)
    finish = s.next("w0")
    assert (finish.kind, finish.job) == ("finish", "a")
    s.done(finish)
    assert "a" not in s.jobs


def test_pausing_or_cancelling_a_job_that_is_not_loaded_needs_no_worker():
    s, clock = make()
    add(s, "a", "alice")
    add(s, "b", "bob")
    assert s.pause("b") is True and s.jobs["b"].phase is Phase.PAUSED
    assert s.cancel("a") is True and "a" not in s.jobs  # never ran: nothing to show
    # a started job that is not loaded is loaded once more, to make its results
    s.resume("b")
    s.done(s.next("w0"))
    step = s.next("w0")
    s.done(step, iterations=step.n)
    evict = Action("evict", "w0", "b")
    s.workers["w0"].action = evict
    s.jobs["b"].busy = True
    s.done(evict)
    assert s.cancel("b") is False
    assert [s.next("w0").kind] == ["load"]


def test_a_job_whose_worker_dies_twice_fails_and_the_others_go_on():
    s, clock = make(workers=2)
    add(s, "bad", "alice")
    add(s, "good", "bob")
    s.done(s.next("w0"))                           # bad loads on w0
    s.done(s.next("w1"))                           # good loads on w1
    s.next("w0")                                   # bad steps...
    lost = s.worker_lost("w0", "died with SIGSEGV during iteration 3")
    assert lost.job == "bad" and not lost.failed   # ...and is retried once
    assert s.jobs["bad"].worker is None
    s.worker_ready("w0")
    again = s.next("w0")
    assert (again.kind, again.job) == ("load", "bad")
    lost = s.worker_lost("w0", "died with SIGSEGV while loading the job")
    assert lost.failed and "bad" not in s.jobs
    assert lost.crashes == ["died with SIGSEGV during iteration 3",
                            "died with SIGSEGV while loading the job"]
    assert s.next("w1").job == "good"              # untouched


def test_a_worker_stopped_on_purpose_costs_its_job_no_retry():
    s, clock = make()
    add(s, "a", "alice")
    s.done(s.next("w0"))
    s.next("w0")
    for _ in range(3):
        lost = s.worker_lost("w0", "stopped", counts=False)
        assert not lost.failed
        s.worker_ready("w0")
        s.next("w0")
    assert s.jobs["a"].crashes == []


def test_jobs_held_by_a_lost_worker_are_requeued_anywhere():
    s, clock = make(workers=2, max_resident=2)
    s.workers["w1"].ready = False
    add(s, "a", "alice")
    add(s, "b", "bob")
    run(s, clock, 10)                                        # both load on w0, take turns
    assert sorted(s.workers["w0"].resident) == ["a", "b"]
    running = s.next("w0")
    lost = s.worker_lost("w0", "died with SIGKILL")
    assert lost.job == running.job and lost.others == [({"a", "b"} - {running.job}).pop()]
    s.worker_ready("w1")
    reload = s.next("w1")
    assert reload.kind == "load" and reload.job in ("a", "b")


def test_tasks_go_before_iterations():
    s, clock = make()
    add(s, "a", "alice")
    s.done(s.next("w0"))
    s.add_task("render preview")
    task = s.next("w0")
    assert (task.kind, task.task) == ("task", "render preview")
    s.done(task)
    assert s.next("w0").kind == "step"



def test_a_task_in_pieces_takes_turns_with_a_job_on_the_worker_that_holds_it():
    """A paused job's standard errors on request (up to a minute) come as pieces for the
    worker that holds their run: each after a turn of the job running there, never on
    another worker, and back to back once no job wants the worker."""
    s, clock = make(workers=2)
    add(s, "a", "alice")
    s.done(s.next("w0"))                                     # a loads on w0
    s.add_task("the estimate's first piece")                 # any worker's: w0 asks first
    first = s.next("w0")
    assert (first.kind, first.task) == ("task", "the estimate's first piece")
    s.done(first)
    kinds = []
    for n in range(3):                                       # each piece queued when the last
        s.add_task(f"piece {n}", worker="w0")                # returned, as a request does
        assert s.next("w1") is None                          # not for the other worker
        for _ in range(2):
            action = s.next("w0")
            kinds.append(action.kind)
            clock.t += COSTS.get(action.kind, ITERATION)
            s.done(action, iterations=1)
    assert kinds == ["step", "task"] * 3                     # alice's turn, then a piece
    s.pause("a")
    s.done(s.next("w0"))                                     # parked: nothing else wants w0
    s.add_task("piece 3", worker="w0")
    s.done(s.next("w0"))
    s.add_task("piece 4", worker="w0")
    assert s.next("w0").task == "piece 4"                    # back to back


def test_a_removed_workers_pieces_go_to_any_worker():
    s, _ = make(workers=2)
    s.add_task("piece", worker="w1")
    s.worker_lost("w1")
    s.remove_worker("w1")
    assert s.next("w0").task == "piece"                      # which says it holds no run

@pytest.mark.parametrize("per_iteration,expected", [(0.001, 250), (0.1, 2), (1.0, 1)])
def test_a_step_call_lasts_about_a_quarter_second(per_iteration, expected):
    s, clock = make()
    add(s, "a", "alice")
    s.done(s.next("w0"))
    first = s.next("w0")
    assert first.n == 1                                      # no pace known yet
    clock.t += per_iteration
    s.done(first, iterations=1)
    assert s.next("w0").n == expected


def test_workers_that_ask_at_once_go_to_different_users():
    # Eight free workers ask before any of them has finished anything (a burst of jobs
    # arriving on an idle cluster): one user with many jobs must not take them all.
    s, _ = make(workers=8)
    for i in range(20):
        add(s, f"big{i}", "alice")
    for user in ("bob", "carol", "dave"):
        add(s, f"{user}0", user)
    actions = [s.next(w) for w in list(s.workers)]
    users = collections.Counter(a.job.rstrip("0123456789") for a in actions)
    assert users["bob"] == users["carol"] == users["dave"] == 1
    assert users["big"] == 5  # the rest: the others have nothing more to run


def test_a_charge_for_work_in_flight_is_refunded_when_it_is_done_or_lost():
    s, clock = make(workers=2)
    add(s, "a", "alice")
    add(s, "b", "bob")
    load_a, load_b = s.next("w0"), s.next("w1")
    assert s.usage["alice"] > 0 and s.usage["bob"] > 0  # charged when they began
    clock.t = 0.4
    s.done(load_a)
    assert s.usage["alice"] == pytest.approx(0.4)  # the estimate replaced by the real time
    s.worker_lost("w1", "died")
    assert s.usage["bob"] == pytest.approx(0.0)  # nothing was done: nothing is owed


def test_an_end_phase_shares_the_worker_with_other_users_jobs():
    """A cancelled job's result images, one sensor per action, and its standard errors, a
    piece per action, take slices like iterations: another user's job goes on stepping
    between them, and the end phase still completes."""
    s, clock = make(slice_seconds=0.5)
    add(s, "a", "alice")
    add(s, "b", "bob")
    run(s, clock, 2.0)                             # both loaded and stepped in turns
    s.cancel("a")
    actions = run(s, clock, 20.0, parts={"a": 8})
    assert [x.job for x in actions if x.kind == "cancel"] == ["a"]
    kinds = [(x.kind, x.job) for x in actions]
    parts = [i for i, k in enumerate(kinds) if k == ("results", "a")]
    assert "a" not in s.jobs
    finish = kinds.index(("finish", "a"))
    assert len(parts) == 8 and finish > parts[-1]
    between = [k for k in kinds[parts[0]:finish] if k == ("step", "b")]
    assert between, kinds                          # bob's job ran during alice's end phase
    assert [x.n for x in actions if x.kind == "results"] == list(range(8))
    pieces = [i for i, k in enumerate(kinds) if k == ("estimate", "a")]
    assert len(pieces) == ESTIMATES and parts[-1] < pieces[0] and pieces[-1] < finish
    # 1.5 s of standard errors against slices of 0.5 s: bob's turns come between the pieces
    assert ("step", "b") in kinds[pieces[0]:pieces[-1]], kinds


def test_a_job_estimating_its_standard_errors_is_not_evicted_for_another():
    """One job per worker: another user's job is due while the first estimates its standard
    errors. Evicted, the first would begin them again (a long job's take up to a minute, so
    they might never end); the job due loads beside it, and the first still finishes."""
    s, clock = make(slice_seconds=0.5)
    add(s, "a", "alice")
    run(s, clock, 0.6)                             # a loaded and stepping
    s.cancel("a")
    estimates: dict[str, int] = collections.Counter()
    actions = run(s, clock, 0.6, parts={"a": 1}, estimates=estimates)  # results, then these
    assert ("estimate", "a") in [(x.kind, x.job) for x in actions]
    add(s, "b", "bob")
    actions += run(s, clock, 10.0, estimates=estimates)
    kinds = [(x.kind, x.job) for x in actions]
    assert ("evict", "a") not in kinds and ("load", "b") in kinds, kinds
    pieces = [i for i, k in enumerate(kinds) if k == ("estimate", "a")]
    assert len(pieces) == ESTIMATES and kinds.index(("finish", "a")) > pieces[-1]
    assert "a" not in s.jobs and s.workers["w0"].resident == ["b"]


def test_standard_errors_lost_with_their_worker_are_estimated_again():
    """The engine keeps a finished estimate for the job's finish; a worker lost between them
    takes it along, so the job, loaded again, estimates anew before it finishes (its finish
    would otherwise estimate them in one action)."""
    s, clock = make()
    add(s, "a", "alice")
    s.done(s.next("w0"))                           # loaded
    s.cancel("a")
    s.done(s.next("w0"))                           # cancel: the end phase begins
    s.end("a", Phase.CANCELLED, "cancelled", 1)
    s.done(s.next("w0"))                           # results
    estimate = s.next("w0")
    s.done(estimate, estimated=True)
    assert s.next("w0").kind == "finish"
    s.worker_lost("w0", "died")                    # in the finish: the run is gone
    s.worker_ready("w0")
    load = s.next("w0")
    assert (load.kind, load.job) == ("load", "a")
    s.done(load)
    assert s.next("w0").kind == "estimate"

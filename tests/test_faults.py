"""Faults cost one job, never the service: real daemons, real worker processes, real signals.

Each test starts its own daemon (two users, alice and bob) so that a worker it kills or stops
affects nothing else in the suite.
"""

from __future__ import annotations

import os
import signal
import threading
import time
from contextlib import contextmanager
from typing import Iterator

import numpy as np
import pytest

from matopt_api.v1 import matopt_pb2 as pb
from matoptd.scheduling.monitor import CANCEL_GRACE_S

from conftest import Daemon, Stubs, TOKENS, token_file, wait_iteration, wait_state
from scenes import create_scene, png, textured_quad

pytestmark = pytest.mark.faults

WALLS = ["red.reflectance.value", "green.reflectance.value"]


@pytest.fixture
def two_users(tmp_path):
    tokens = token_file(tmp_path)
    daemons = []

    def start(*extra: str) -> tuple[Daemon, Stubs, Stubs]:
        d = Daemon(tmp_path / f"data{len(daemons)}", tokens, *extra).start()
        daemons.append(d)
        return d, Stubs(d.address, TOKENS["alice"]), Stubs(d.address, TOKENS["bob"])

    yield start
    for d in daemons:
        d.stop()


def cornell_job(stubs: Stubs, iterations: int, res: int = 32, spp: int = 4, **spec) -> pb.Job:
    scene = stubs.scenes.CreateScene(pb.CreateSceneRequest(
        overrides={"resx": str(res), "resy": str(res)}))
    ref = stubs.scenes.RenderScene(pb.RenderSceneRequest(name=scene.name, spp=32)).images[0]
    return stubs.jobs.CreateJob(pb.CreateJobRequest(spec=pb.JobSpec(
        scene=scene.name, iterations=iterations, spp=spp,
        references=[pb.Reference(blob=ref.exr_blob, filename="ref.exr")],
        parameters=[pb.ParameterSpec(key=k, initial_value=[0.5] * 3) for k in WALLS], **spec)))


def worker(stubs: Stubs, index: int = 0) -> pb.Worker:
    return stubs.server.GetServerInfo(pb.GetServerInfoRequest()).workers[index]


@contextmanager
def frozen(pid: int, then: int = signal.SIGCONT) -> Iterator[None]:
    """The process stopped (SIGSTOP: alive, answering nothing), then sent ``then``."""
    os.kill(pid, signal.SIGSTOP)
    try:
        yield
    finally:
        try:
            os.kill(pid, then)
        except ProcessLookupError:
            pass


def wait_worker(stubs: Stubs, states, timeout: float = 120) -> pb.Worker:
    deadline = time.time() + timeout
    while time.time() < deadline:
        w = worker(stubs)
        if w.state in states and w.pid:
            return w
        time.sleep(0.1)
    raise AssertionError(f"worker did not reach {states}: {w}")


class Poller:
    """Polls GetJob every 50 ms from another thread and counts failed calls: the API must
    answer throughout a worker's death and restart."""

    def __init__(self, stubs: Stubs, name: str) -> None:
        self.stubs, self.name, self.calls, self.errors = stubs, name, 0, []
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while not self.stop.is_set():
            try:
                self.stubs.jobs.GetJob(pb.GetJobRequest(name=self.name), timeout=5)
                self.calls += 1
            except Exception as exc:  # noqa: BLE001 - counted and asserted on
                self.errors.append(exc)
            time.sleep(0.05)

    def finish(self) -> None:
        self.stop.set()
        self.thread.join()


def test_kill_9_of_a_worker_costs_no_job(two_users):
    daemon, alice, bob = two_users()
    a = cornell_job(alice, 150)
    b = cornell_job(bob, 150)
    poller = Poller(alice, a.name)
    wait_iteration(alice, a.name, 15)
    # One step more: the step that crossed iteration 10 has written its checkpoint by then
    # (records are published before a checkpoint is written).
    wait_iteration(bob, b.name, wait_iteration(bob, b.name, 15).iteration + 1)
    victim = wait_worker(alice, (pb.WORKER_STATE_BUSY, pb.WORKER_STATE_IDLE))
    os.kill(victim.pid, signal.SIGKILL)

    done_a = wait_state(alice, a.name, (pb.JOB_STATE_SUCCEEDED, pb.JOB_STATE_FAILED), timeout=300)
    done_b = wait_state(bob, b.name, (pb.JOB_STATE_SUCCEEDED, pb.JOB_STATE_FAILED), timeout=300)
    poller.finish()
    assert poller.errors == [] and poller.calls > 20  # the API answered all along
    assert (done_a.state, done_b.state) == (pb.JOB_STATE_SUCCEEDED, pb.JOB_STATE_SUCCEEDED), (done_a, done_b)
    notes = [n for j in (done_a, done_b) for n in j.notes if "SIGKILL" in n]
    assert notes and "goes on from its last checkpoint" in notes[0]
    assert any(j.resumed_from.startswith("checkpoint at iteration") for j in (done_a, done_b)), \
        [(j.resumed_from, list(j.notes)) for j in (done_a, done_b)]
    for job, stubs in ((done_a, alice), (done_b, bob)):
        history = stubs.jobs.GetJobHistory(pb.GetJobHistoryRequest(name=job.name)).iterations
        assert [r.iteration for r in history] == list(range(150))  # no gap, no repeat
    after = wait_worker(alice, (pb.WORKER_STATE_IDLE,))
    assert after.restarts == 1 and after.pid != victim.pid
    assert "SIGKILL" in after.last_exit


def test_a_job_over_the_memory_limit_fails_that_job_only(two_users):
    daemon, alice, bob = two_users("--worker-memory", "450M")
    small = cornell_job(bob, 60)
    wait_iteration(bob, small.name, 5)
    # A 2048x2048 texture with its gradient and Adam's two moments: far more than 450 MiB.
    # Its reference comes from a small texture: rendering the huge one alone nears the limit.
    ref = alice.scenes.RenderScene(pb.RenderSceneRequest(
        name=texture_scene(alice, 64, seed=0).name, spp=1)).images[0]
    scene = texture_scene(alice, 2048, seed=0)
    huge = alice.jobs.CreateJob(pb.CreateJobRequest(spec=pb.JobSpec(
        scene=scene.name, iterations=5, spp=1, references=[pb.Reference(blob=ref.exr_blob)],
        parameters=[pb.ParameterSpec(key="quad.bsdf.reflectance.data")])))
    failed = wait_state(alice, huge.name, (pb.JOB_STATE_FAILED, pb.JOB_STATE_SUCCEEDED), timeout=300)
    assert failed.state == pb.JOB_STATE_FAILED
    assert "exceeded the worker memory limit of 450.0 MiB" in failed.error, failed.error
    assert "--worker-memory" in failed.error
    done = wait_state(bob, small.name, (pb.JOB_STATE_SUCCEEDED, pb.JOB_STATE_FAILED), timeout=300)
    assert done.state == pb.JOB_STATE_SUCCEEDED, done
    after = wait_worker(bob, (pb.WORKER_STATE_IDLE,))
    assert after.memory_limit_bytes == 450 << 20 and "memory limit" in after.last_exit


def test_a_hung_iteration_is_cut_off_by_the_watchdog(two_users):
    daemon, alice, bob = two_users("--watchdog", "3")
    job = cornell_job(alice, 120)
    wait_iteration(alice, job.name, 20)
    hung = wait_worker(alice, (pb.WORKER_STATE_BUSY, pb.WORKER_STATE_IDLE))
    with frozen(hung.pid, signal.SIGKILL):  # alive, but answering nothing: a wedged renderer
        done = wait_state(alice, job.name, (pb.JOB_STATE_SUCCEEDED, pb.JOB_STATE_FAILED), timeout=300)
    assert done.state == pb.JOB_STATE_SUCCEEDED, done
    assert any("stopped answering" in n for n in done.notes), done.notes
    assert worker(alice).restarts == 1


def texture_scene(stubs: Stubs, size: int, seed: int) -> pb.Scene:
    """A textured quad; the texture is smooth (a small PNG) but ``size`` texels wide."""
    y, x = np.mgrid[0:size, 0:size] / size
    pixels = np.stack([0.2 + 0.6 * x, 0.2 + 0.6 * y, np.full_like(x, 0.2 + 0.1 * seed)], -1)
    return create_scene(stubs, {"scene.xml": textured_quad(32).encode(),
                                "textures/albedo.png": png(pixels)}, "scene.xml")


def test_paused_jobs_give_their_memory_back(two_users):
    daemon, alice, bob = two_users("--workers", "1")
    idle = wait_worker(alice, (pb.WORKER_STATE_IDLE,)).memory_bytes
    key = "quad.bsdf.reflectance.data"
    jobs = []
    for seed in range(3):
        scene = texture_scene(alice, 1024, seed)
        ref = alice.scenes.RenderScene(pb.RenderSceneRequest(name=scene.name, spp=4)).images[0]
        jobs.append(alice.jobs.CreateJob(pb.CreateJobRequest(spec=pb.JobSpec(
            scene=scene.name, iterations=1000, spp=1,
            references=[pb.Reference(blob=ref.exr_blob)],
            parameters=[pb.ParameterSpec(key=key)]))))
    for job in jobs:
        wait_iteration(alice, job.name, 3)
    loaded = worker(alice).memory_bytes
    for job in jobs:
        alice.jobs.PauseJob(pb.PauseJobRequest(name=job.name))
    for job in jobs:
        wait_state(alice, job.name, (pb.JOB_STATE_PAUSED,))
    time.sleep(0.5)
    paused = wait_worker(alice, (pb.WORKER_STATE_IDLE,))
    assert paused.job_count == 0
    # A job's 1024x1024 texture with Adam's state is ~70 MB; released, the worker is back
    # near where it started.
    assert loaded - idle > 60 << 20, (idle, loaded)
    assert paused.memory_bytes < idle + (40 << 20), (idle, loaded, paused.memory_bytes)
    at = alice.jobs.ResumeJob(pb.ResumeJobRequest(name=jobs[0].name)).iteration
    resumed = wait_iteration(alice, jobs[0].name, at + 2)
    assert resumed.resumed_from == f"checkpoint at iteration {at}"


def test_a_paused_job_goes_on_with_the_losses_it_would_have_had(two_users):
    """Pause releases the job's run; resume reloads it from the checkpoint (on a worker with
    one thread, where Dr.Jit's sums are deterministic): the same losses as without a pause."""
    daemon, alice, bob = two_users("--workers", "2")
    plain = cornell_job(alice, 40, seed=7)
    wait_state(alice, plain.name, (pb.JOB_STATE_SUCCEEDED,), timeout=300)
    paused = alice.jobs.CreateJob(pb.CreateJobRequest(spec=plain.spec))
    wait_iteration(alice, paused.name, 12)
    alice.jobs.PauseJob(pb.PauseJobRequest(name=paused.name))
    at = wait_state(alice, paused.name, (pb.JOB_STATE_PAUSED,)).iteration
    assert 12 <= at < 40
    alice.jobs.ResumeJob(pb.ResumeJobRequest(name=paused.name))
    done = wait_state(alice, paused.name, (pb.JOB_STATE_SUCCEEDED,), timeout=300)
    # It did go through its checkpoint (else the comparison below proves nothing).
    assert done.resumed_from == f"checkpoint at iteration {at}", done.resumed_from
    losses = [[r.loss for r in alice.jobs.GetJobHistory(pb.GetJobHistoryRequest(
        name=j.name)).iterations] for j in (plain, paused)]
    assert len(losses[0]) == len(losses[1]) == 40
    # The same up to the last bit of a float32 sum, whose order across threads varies.
    np.testing.assert_allclose(losses[1], losses[0], rtol=1e-6)


def test_the_server_process_never_loads_the_renderer(two_users):
    daemon, alice, bob = two_users()
    job = cornell_job(alice, 5)
    wait_state(alice, job.name, (pb.JOB_STATE_SUCCEEDED,))
    maps = open(f"/proc/{daemon.proc.pid}/maps").read()
    assert "libdrjit" not in maps and "libmitsuba" not in maps and "mitsuba" not in maps
    w = worker(alice)
    worker_maps = open(f"/proc/{w.pid}/maps").read()
    assert "libdrjit" in worker_maps  # the check above can see them where they are


def test_a_long_iteration_cancelled_after_short_ones_keeps_what_they_finished(two_users,
                                                                              tmp_path):
    """Short iterations, then one that does not end (its worker frozen with SIGSTOP, as a
    render of minutes looks to the daemon): the cancel stops the worker within seconds, and
    the iterations that finished are the job's LAST and BEST, exportable."""
    import json

    from matopt_client.client import connect
    from matopt_client.export import export_job

    daemon, alice, bob = two_users()
    job = cornell_job(alice, 500)
    wait_iteration(alice, job.name, 3)
    busy = wait_worker(alice, (pb.WORKER_STATE_BUSY,))
    with frozen(busy.pid):  # the iteration in flight now never ends
        time.sleep(0.5)  # a step that had just returned is recorded
        began = time.monotonic()
        alice.jobs.CancelJob(pb.CancelJobRequest(name=job.name))
        done = wait_state(alice, job.name, (pb.JOB_STATE_CANCELLED, pb.JOB_STATE_FAILED),
                          timeout=60)
        took = time.monotonic() - began
    assert done.state == pb.JOB_STATE_CANCELLED, done
    assert took < CANCEL_GRACE_S + 10.0, f"the cancel took {took:.1f} s"
    assert done.iteration >= 3
    history = alice.jobs.GetJobHistory(pb.GetJobHistoryRequest(name=job.name)).iterations
    assert [r.iteration for r in history] == list(range(done.iteration))
    for which in (pb.WHICH_LAST, pb.WHICH_BEST):
        result = alice.jobs.GetJobResult(pb.GetJobResultRequest(name=job.name, which=which))
        expected = history[-1] if which == pb.WHICH_LAST else history[done.best_iteration]
        assert result.iteration == expected.iteration
        assert flat(result.parameters) == pytest.approx(flat(expected.parameters))
        assert flat(result.initial_parameters) == pytest.approx([0.5] * 6)
    client = connect(daemon.address, TOKENS["alice"])
    try:
        export_job(client, job.name, tmp_path / "out", "last")
    finally:
        client.close()
    written = json.loads((tmp_path / "out" / "parameters.json").read_text())
    assert written["iteration"] == done.iteration - 1
    assert [x for k in WALLS for x in written["parameters"][k]] == pytest.approx(
        flat(history[-1].parameters))


def test_a_paused_job_shows_what_it_finished(two_users):
    daemon, alice, bob = two_users()
    job = cornell_job(alice, 500)
    wait_iteration(alice, job.name, 3)
    alice.jobs.PauseJob(pb.PauseJobRequest(name=job.name))
    paused = wait_state(alice, job.name, (pb.JOB_STATE_PAUSED,), timeout=60)
    history = alice.jobs.GetJobHistory(pb.GetJobHistoryRequest(name=job.name)).iterations
    last = alice.jobs.GetJobResult(pb.GetJobResultRequest(name=job.name, which=pb.WHICH_LAST))
    assert last.iteration == paused.iteration - 1 == history[-1].iteration
    assert flat(last.parameters) == pytest.approx(flat(history[-1].parameters))


def flat(values) -> list[float]:
    """The walls' values, one list (red, then green)."""
    by_key = {v.key: list(v.value) for v in values}
    return [x for k in WALLS for x in by_key[k]]

"""Stand-ins for what the scheduling drives, so that its lanes, recovery and job control run in
one thread with a fake clock: an engine whose iterations only count, a worker that calls it in
process (and can be made to die or be stopped during a call), and a store in memory.

The fake engine keeps the contract of ``engine_api.Engine`` that the daemon relies on: a
checkpoint continues a run exactly (iteration i always has loss 1 / (i + 1)), and a worker that
is lost forgets every run it held.
"""

from __future__ import annotations

import copy
import hashlib
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable

import numpy as np

from matoptd import engine_api as api
from matoptd.errors import DiskFull, NotFound
from matoptd.records import JobRecord, Phase, ResultRecord, SceneRecord
from matoptd.settings import JobSettings, ParameterSetting, ReferenceInput, SceneInput
from matoptd.workers.devices import Placement
from matoptd.workers.handle import CallFailed, WorkerLost

SCENE = SceneInput.of("s.xml", {"s.xml": "0" * 64}, {}, "s.xml")
KEY = "red.reflectance.value"


def settings(iterations: int, sensors: int = 1) -> JobSettings:
    return JobSettings(SCENE, [ReferenceInput(s, f"{s:064x}", f"ref{s}.exr")
                               for s in range(sensors)],
                       [ParameterSetting(KEY, 0.1, 0.0, 1.0)], iterations=iterations)


def job(name: str, owner: str = "alice", iterations: int = 50, sensors: int = 1) -> JobRecord:
    return JobRecord(f"jobs/{name}", owner, "scenes/s", settings(iterations, sensors))


class Clock:
    """Both clocks of ``scheduling.state.Clock``, moved by hand (and by the fake engine)."""

    def __init__(self) -> None:
        self.t = 1000.0

    def monotonic(self) -> float:
        return self.t

    def time(self) -> float:
        return 1.8e9 + self.t


ESTIMATE_PARTS = 3  # the fake engine's standard errors take this many estimate_part calls


@dataclass
class Run:
    settings: JobSettings
    iteration: int
    estimated: int = 0  # estimate_part calls so far


class FakeEngine:
    """Iteration i of any job has loss 1 / (i + 1) and value i / 100, and takes ``seconds``
    of the fake clock."""

    def __init__(self, clock: Clock, seconds: float = 0.1) -> None:
        self.clock, self.seconds = clock, seconds
        self.runs: dict[str, Run] = {}
        self.started: list[tuple[str, int]] = []  # (job, iteration it went on from)

    def describe_scene(self, scene: SceneInput) -> api.SceneDescription:
        return api.SceneDescription([api.SensorInfo(0, "", 8, 8)], False, [])

    def render(self, scene: SceneInput, request: api.RenderRequest) -> list[api.Image]:
        return []

    def check_references(self, references: list[ReferenceInput]) -> None:
        pass

    def start(self, job: str, settings: JobSettings, checkpoint: bytes | None) -> api.Started:
        at = int(checkpoint) if checkpoint else 0
        self.runs[job] = Run(settings, at)
        self.started.append((job, at))
        sensors = [r.sensor for r in settings.references]
        return api.Started(at, "prb", "a fake", sensors, [], {KEY: [3]}, {KEY: "rgb"})

    def step(self, job: str, n: int) -> api.Progress:
        run = self.runs[job]
        records = []
        while len(records) < n and run.iteration < run.settings.iterations:
            i = run.iteration
            self.clock.t += self.seconds
            records.append(api.IterationRecord(i, i * self.seconds, 1 / (i + 1),
                                               {KEY: np.full(3, i / 100, np.float32)}))
            run.iteration += 1
        done = run.iteration >= run.settings.iterations
        last = records[-1]
        return api.Progress(records, done, "iterations" if done else "", last.iteration,
                            last.loss, last.seconds, api.Counters())

    def checkpoint(self, job: str) -> bytes:
        return str(self.runs[job].iteration).encode()

    def result_images(self, job: str, sensor: int) -> dict[str, list[api.Image]]:
        image = api.Image(sensor, "optimized", 8, 8, b"exr %d" % sensor, b"png %d" % sensor)
        return {"best": [image], "last": [image]}

    def estimate_part(self, job: str, seconds: float) -> bool:
        """Standard errors in ``ESTIMATE_PARTS`` pieces, as a long job's end takes them."""
        run = self.runs[job]
        run.estimated += 1
        return run.estimated >= ESTIMATE_PARTS

    def finish(self, job: str, history: list[api.IterationRecord], cancelled: bool,
               render: bool = True) -> api.Finished:
        last = self.runs[job].iteration - 1
        results = [api.Result(which, last, 1 / (last + 1), {KEY: np.full(3, last / 100)},
                              {KEY: np.zeros(3)}, [], {"scene_optimized.xml": b"<scene/>"},
                              "scene_optimized.xml", []) for which in ("best", "last")]
        return api.Finished(results if last >= 0 else [], [f"{len(history)} records"],
                            api.Counters())

    def release(self, job: str) -> None:
        self.runs.pop(job, None)


@dataclass
class FakeWorker:
    """A worker whose calls run the fake engine in this thread. ``before`` is called with
    each call's method and arguments before it runs: a test does there what happens while the
    call is in flight (a handler's pause, the worker dying, the monitor stopping it)."""

    name: str
    engine: FakeEngine
    placement: Placement = Placement(None, (0,), 1)
    memory_limit: int = 1 << 30
    state: str = "starting"
    info: dict = field(default_factory=dict)
    restarts: int = 0
    last_exit: str = ""
    node: str = ""
    gone: bool = False
    before: Callable[[str, tuple], None] | None = None
    calls: list[str] = field(default_factory=list)
    _killed: tuple[str, str] | None = None

    @property
    def pid(self) -> int:
        return 4242 if self.state in ("idle", "busy") else 0

    def start(self) -> None:
        self.engine.runs.clear()  # a fresh process holds nothing
        self._killed, self.state = None, "idle"

    def stop(self) -> None:
        self.state = "stopped"

    def kill(self, reason: str, cause: str) -> None:
        self._killed = (reason, cause)

    def die(self, reason: str = "died with SIGSEGV", cause: str = "died") -> None:
        """The process ends during the call in flight."""
        self._killed = (reason, cause)

    def memory(self) -> int:
        return 0

    def check_memory(self) -> None:
        pass

    def call(self, method: str, *args: Any, timeout: float | None = None) -> Any:
        self.calls.append(method)
        self.state = "busy"
        if self.before is not None:
            self.before(method, args)
        if self._killed is not None:
            reason, _ = self._killed
            self.state, self.last_exit = "restarting", reason
            raise WorkerLost(*self._killed)
        try:
            return getattr(self.engine, method)(*args)
        except api.InvalidInput as exc:
            raise CallFailed("invalid", str(exc)) from None
        finally:
            if self.state == "busy":
                self.state = "idle"


class MemoryBlobs:
    def __init__(self) -> None:
        self.data: dict[str, bytes] = {}

    def put(self, data: bytes, owner: str) -> str:
        sha = hashlib.sha256(data).hexdigest()
        self.data[sha] = data
        return sha


class MemoryCheckpoints:
    def __init__(self) -> None:
        self.files: dict[str, bytes] = {}

    def write(self, job: str, data: bytes) -> None:
        self.files[job] = data

    def read(self, job: str) -> bytes | None:
        return self.files.get(job)

    def exists(self, job: str) -> bool:
        return job in self.files

    def size(self, job: str) -> int:
        return len(self.files.get(job, b""))


class MemoryDisk:
    def __init__(self) -> None:
        self.full_since: float | None = None
        self.free = True

    def space_back(self, held: int = 0) -> bool:
        if self.full_since is not None and self.free:
            self.full_since = None
        return self.full_since is None

    def write(self) -> None:
        """Raises DiskFull as a write to a full disk does."""
        if not self.free:
            self.full_since = self.full_since or 1.0
            raise DiskFull()


class MemoryStore:
    """``scheduling.state.JobStore`` in memory; records are copied in and out, as a store
    keeps what it was given when it was given."""

    def __init__(self) -> None:
        self.blobs, self.checkpoints, self.disk = MemoryBlobs(), MemoryCheckpoints(), MemoryDisk()
        self.jobs: dict[str, JobRecord] = {}
        self.iterations: dict[str, dict[int, api.IterationRecord]] = {}
        self.results: dict[tuple[str, str], ResultRecord] = {}
        self.scene = SceneRecord("scenes/s", "alice", "s", "s.xml", [], {}, [], [], False, 1,
                                 SCENE)

    def add_job(self, job: JobRecord, request_id: str | None) -> None:
        self.jobs[job.name] = copy.deepcopy(job)

    def put_job(self, job: JobRecord) -> None:
        self.disk.write()
        if job.name in self.jobs:
            self.jobs[job.name] = copy.deepcopy(job)

    def get_job(self, name: str, owner: str | None = None) -> JobRecord:
        job = self.jobs.get(name)
        if job is None or (owner is not None and job.owner != owner):
            raise NotFound(f"job '{name}' not found")
        return copy.deepcopy(job)

    def list_jobs(self, owner: str | None, offset: int = 0, limit: int = -1,
                  phases: Iterable[Phase] = ()) -> list[JobRecord]:
        phases = set(phases)
        return [copy.deepcopy(j) for j in self.jobs.values()
                if (owner is None or j.owner == owner) and (not phases or j.phase in phases)]

    def delete_job(self, name: str) -> None:
        self.jobs.pop(name, None)

    def add_iterations(self, job: str, records: list[api.IterationRecord]) -> None:
        self.disk.write()
        self.iterations.setdefault(job, {}).update({r.iteration: r for r in records})

    def history(self, job: str, offset: int = 0, limit: int = -1) -> list[api.IterationRecord]:
        return [r for _, r in sorted(self.iterations.get(job, {}).items())]

    def truncate_history(self, job: str, keep_below: int) -> None:
        kept = self.iterations.get(job, {})
        self.iterations[job] = {i: r for i, r in kept.items() if i < keep_below}

    def put_result(self, result: ResultRecord) -> None:
        self.results[(result.job, result.which)] = copy.deepcopy(result)

    def get_scene(self, owner: str, name: str) -> SceneRecord:
        return self.scene

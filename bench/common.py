"""What every benchmark case shares: a daemon in a child process, a client, scenes and
references, running a job while timing it on both sides, alternation, statistics and CSV.

Machines here are noisy (2 shared cores), so no case reports an absolute time alone: each
measures its baseline in the same run, alternating with the measured thing (A B, B A, ...),
and reports the ratio.
"""

from __future__ import annotations

import csv
import ctypes
import os
import signal
import statistics
import subprocess
import sys
import threading
import time
import uuid
import xml.etree.ElementTree as ET
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator, Sequence

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))  # tests/scenes.py: the procedural scenes

from matopt_client import client as mc  # noqa: E402
from matopt_client.cli import report  # noqa: E402
from matopt_api.v1 import matopt_pb2 as pb  # noqa: E402

CORNELL_XML = ROOT / "daemon" / "matoptd" / "engine" / "cornell_box.xml"
WALLS = ["red.reflectance.value", "green.reflectance.value"]
GREY = [0.5, 0.5, 0.5]


# ---------------------------------------------------------------------------------------------
# Results of a case
# ---------------------------------------------------------------------------------------------


@dataclass
class Target:
    """A figure against its target; ``met`` None when it could not be measured."""

    what: str
    figure: str
    met: bool | None


@dataclass
class Result:
    """What a case hands to the summary: targets, a few markdown lines, files it wrote."""

    name: str
    title: str
    targets: list[Target] = field(default_factory=list)
    lines: list[str] = field(default_factory=list)
    files: list[Path] = field(default_factory=list)
    seconds: float = 0.0


@dataclass
class Settings:
    out: Path
    quick: bool
    work: Path  # scratch space (daemon data dirs, downloads): not part of the results
    thesis_size: bool = False  # thesis_tables at the thesis's image size (a GPU's work)
    thesis_repo: Path | None = None  # a checkout of the thesis's repository (real_scenes)
    variant: str = ""          # the daemons' --variant ("": as they pick it)
    film: tuple[int, int] | None = None  # real_scenes: film width and height
    iterations: int = 0        # real_scenes: iterations per run (0: by device)
    seeds: int = 0             # real_scenes: seeds (0: 3)
    tables: tuple[str, ...] = ()  # real_scenes: the tables run (empty: all)
    defaults_only: bool = False  # real_scenes: the plain loop and the defaults, nothing else
    cost_only: bool = False    # calibration: the standard errors' cost alone
    deadline: float = 0.0      # real_scenes: epoch seconds by which to end (0: none)
    # real_scenes, defaults_matrix: a daemon job per seed with these choices turned on or off
    # beside the defaults (NAME=VALUE, e.g. gauss_newton=on)
    with_choices: dict[str, str] = field(default_factory=dict)
    # real_scenes, defaults_matrix: the seeds run are first_seed, first_seed + 1, ...
    first_seed: int = 0
    spps: tuple[int, ...] = ()  # defaults_matrix: the spp of its cells (empty: its corner)
    depths: tuple[int, ...] = ()  # defaults_matrix: the max_depth of its cells (empty: all)
    tutorials_repo: Path | None = None  # a checkout of mitsuba-tutorials (tutorials)
    # defaults_matrix: the with_choices job in the defaults' place, judged as they are (the
    # plain loop at equal time runs for its time; no plain run at equal iterations)
    candidate_only: bool = False
    # defaults_matrix: every run's values per iteration kept (defaults_matrix-paths.jsonl), so
    # that an estimate made from a job's path (an average of its end) is judged on the same runs
    paths: bool = False
    # real_scenes, defaults_matrix: the daemon's jobs given the thesis's bounds the plain loop
    # runs with (Table 4's eta at most 1.55, its start), so that both sides solve one problem
    thesis_bounds: bool = True


# ---------------------------------------------------------------------------------------------
# The daemon
# ---------------------------------------------------------------------------------------------


@dataclass
class Daemon:
    process: subprocess.Popen
    client: mc.Client
    address: str
    data_dir: Path
    log: Path
    tokens: dict[str, str] = field(default_factory=dict)  # user -> token, with --tokens
    _children: list[int] = field(default_factory=list)

    @property
    def pid(self) -> int:
        """The server process: gRPC, store, scheduler; never the renderer."""
        return self.process.pid

    @property
    def variant(self) -> str:
        return self.client.info.variant if self.client.info else ""

    @property
    def cuda(self) -> bool:
        return self.variant.startswith("cuda")

    def connect(self, user: str | None = None) -> mc.Client:
        """Another client of this daemon, as ``user`` (a name in ``tokens``) when given."""
        return mc.connect(self.address, self.tokens[user] if user else None,
                          probe_timeout=30)

    def worker_pids(self) -> list[int]:
        """The renderer processes the daemon runs now, from GetServerInfo (0: none running)."""
        info = self.client.server.GetServerInfo(pb.GetServerInfoRequest(), timeout=30)
        return [w.pid for w in info.workers if w.pid]

    def cpu(self) -> "Cpu":
        """CPU seconds so far of the server process and of its worker processes (each
        worker that runs now: a restarted worker's predecessor no longer counts)."""
        return Cpu(cpu_seconds(self.pid), sum(cpu_seconds(p) for p in self.workers()))

    def rss(self) -> tuple[int, int]:
        """Resident bytes of the server process and of all its workers together."""
        return rss_bytes(self.pid), sum(rss_bytes(p) for p in self.workers())

    def workers(self) -> list[int]:
        """The pids of the worker processes (the daemon's children), looked up again only
        when one of those known has ended: reading /proc for every process is not free."""
        if not self._children or not all(Path(f"/proc/{p}").exists() for p in self._children):
            self._children = children(self.pid)
        return self._children


def tokens_file(path: Path, users: Sequence[str]) -> dict[str, str]:
    """A ``--tokens`` file with one token per user (the daemon wants >= 16 characters)."""
    tokens = {u: f"{u}-{uuid.uuid4().hex}" for u in users}
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(f"{t} {u}\n" for u, t in tokens.items()))
    return tokens


try:  # resolved here: between fork and exec the child may take no lock (dlopen's included)
    _PRCTL = ctypes.CDLL(None, use_errno=True).prctl
except (OSError, AttributeError):  # not Linux
    _PRCTL = None


def _die_with_parent() -> None:
    """SIGTERM to the daemon when the bench process ends, however it ends: a bench stopped
    by a signal skips its ``finally``, and a daemon left running would load every later
    measurement on the machine."""
    if _PRCTL is not None:
        _PRCTL(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


@contextmanager
def daemon(work: Path, name: str = "daemon", extra: Sequence[str] = (),
           users: Sequence[str] = (), env: dict[str, str] | None = None) -> Iterator[Daemon]:
    """``python -m matoptd`` on a free loopback port with its own data dir, as users start it,
    with ``extra`` flags; with ``users``, a tokens file for them (``client`` is the first
    user's); ``env``: its environment (another checkout's PYTHONPATH), else this one's.
    SIGTERM on the way out (SIGKILL if it does not stop in 60 s)."""
    directory = work / f"{name}-{uuid.uuid4().hex[:6]}"
    directory.mkdir(parents=True)
    port_file, log = directory / "port", directory / "matoptd.log"
    command = [sys.executable, "-m", "matoptd", "--listen", "127.0.0.1:0",
               "--data-dir", str(directory / "data"), "--port-file", str(port_file), *extra]
    tokens = tokens_file(directory / "tokens", users) if users else {}
    if tokens:
        command += ["--tokens", str(directory / "tokens")]
    with open(log, "wb") as out:
        process = subprocess.Popen(command, stdin=subprocess.DEVNULL, stdout=out,
                                   stderr=subprocess.STDOUT, preexec_fn=_die_with_parent,
                                   env=env)
    try:
        deadline = time.monotonic() + 180
        while not port_file.exists():
            if process.poll() is not None:
                raise RuntimeError(f"matoptd exited: {log.read_text()[-2000:]}")
            if time.monotonic() > deadline:
                raise RuntimeError("matoptd did not start in 180 s")
            time.sleep(0.1)
        address = f"127.0.0.1:{int(port_file.read_text())}"
        client = mc.connect(address, tokens[users[0]] if tokens else None, probe_timeout=30)
        try:
            yield Daemon(process, client, address, directory / "data", log, tokens)
        finally:
            client.close()
    finally:
        if process.poll() is None:
            process.send_signal(signal.SIGTERM)
            try:
                process.wait(60)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()


@dataclass(frozen=True)
class Cpu:
    """CPU seconds of the daemon's two kinds of process: the server (gRPC, store, scheduler)
    and the workers (the renderer). A job's own work is the workers'."""

    server: float
    workers: float


def children(pid: int) -> list[int]:
    """The live child processes of ``pid``: the processes whose parent it is (Linux /proc)."""
    out = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:  # ended meanwhile
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                out.append(int(entry.name))
    return out


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process, all its threads (Linux /proc); 0 once it is gone."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def rss_bytes(pid: int) -> int:
    """Resident set size of a process: psutil when installed, else /proc (Linux)."""
    try:
        import psutil
        return psutil.Process(pid).memory_info().rss
    except ImportError:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    raise RuntimeError(f"cannot read the RSS of process {pid}")


# ---------------------------------------------------------------------------------------------
# Scenes, references, jobs
# ---------------------------------------------------------------------------------------------


def cornell(client: mc.Client, res: int) -> pb.Scene:
    """The daemon's built-in Cornell box at res x res."""
    return client.scenes.CreateScene(pb.CreateSceneRequest(
        overrides={"resx": str(res), "resy": str(res)}, request_id=str(uuid.uuid4())))


def xml_scene(client: mc.Client, work: Path, xml: str, name: str,
              **overrides: object) -> pb.Scene:
    """A one-file scene bundle from an XML string (uploaded like any user's scene)."""
    path = work / "scenes" / f"{name}-{uuid.uuid4().hex[:6]}" / f"{name}.xml"
    path.parent.mkdir(parents=True)
    path.write_text(xml)
    main, files = mc.upload_bundle(client, path)
    return client.scenes.CreateScene(pb.CreateSceneRequest(
        main_file=main, files=files, overrides={k: str(v) for k, v in overrides.items()},
        request_id=str(uuid.uuid4())))


def with_ids(xml: str) -> str:
    """The XML with the ids the daemon gives unnamed top-level objects, so that a plain
    Mitsuba script sees the same parameter keys as a job."""
    from matoptd.server.bundles import assign_ids  # pure XML, no Mitsuba
    root = ET.fromstring(xml)
    assign_ids(root)
    return ET.tostring(root, encoding="unicode")


def parameters(client: mc.Client, scene: pb.Scene) -> dict[str, pb.Parameter]:
    return {p.key: p for p in client.scenes.ListSceneParameters(
        pb.ListSceneParametersRequest(name=scene.name)).parameters}


def reference(client: mc.Client, scene: pb.Scene, spp: int, work: Path) -> tuple[str, Path]:
    """A reference render of sensor 0 by the daemon: its EXR blob and a local copy (for the
    plain Mitsuba loops, which must fit the very same image)."""
    image = client.scenes.RenderScene(pb.RenderSceneRequest(
        name=scene.name, spp=spp, sensors=[0], seed=12345)).images[0]
    path = work / "references" / f"{image.exr_blob.removeprefix('blobs/')}.exr"
    if not path.exists():
        mc.download_blob(client, image.exr_blob, path)
    return image.exr_blob, path


def bundle_scene(client: mc.Client, xml: Path) -> pb.Scene:
    """A scene from an XML file and the files beside it it names, uploaded as a user would."""
    main, files = mc.upload_bundle(client, xml)
    return client.scenes.CreateScene(pb.CreateSceneRequest(main_file=main, files=files))


def every_reference(client: mc.Client, xml: Path, spp: int
                    ) -> tuple[list[pb.Image], dict[int, Path]]:
    """The references of every sensor of the scene in ``xml``, rendered by the daemon: the
    images (their EXR blobs, for jobs) and local copies beside ``xml`` (for plain loops)."""
    images = list(client.scenes.RenderScene(pb.RenderSceneRequest(
        name=bundle_scene(client, xml).name, spp=spp, seed=12345)).images)
    paths = {i.sensor: xml.parent / f"ref{i.sensor}.exr" for i in images}
    for image in images:
        mc.download_blob(client, image.exr_blob, paths[image.sensor])
    return images, paths


@dataclass
class JobRun:
    """A finished job with its history, and when the client saw each iteration arrive."""

    job: pb.Job
    history: list[pb.IterationRecord]
    wall: float                     # CreateJob sent -> final state seen
    arrivals: list[float]           # client clock of each iteration event, from CreateJob
    first_iteration: float | None   # CreateJob sent -> iteration 0 seen
    cpu: list[Cpu] = field(default_factory=list)  # the daemon's CPU seconds at each arrival

    @property
    def seconds(self) -> list[float]:
        return [r.seconds for r in self.history]

    @property
    def cpu_server(self) -> list[float]:
        return [c.server for c in self.cpu]

    @property
    def cpu_workers(self) -> list[float]:
        return [c.workers for c in self.cpu]


def run_job(client: mc.Client, spec: pb.JobSpec,
            on_created: Callable[[str], None] | None = None,
            server: Daemon | None = None) -> JobRun:
    """Creates the job and follows it with WatchJob to its end.

    The watch starts right after CreateJob returns (and ``on_created(name)``); should
    iteration 0 have finished before the stream opened, the job event that opens the stream
    shows it, so first_iteration is never missed (only then it is a little late). With the
    daemon (``server``), the CPU time of its server and worker processes is read as each
    iteration arrives: work done, which other tenants of the machine disturb far less than
    elapsed time.
    """
    began = time.perf_counter()
    name = client.jobs.CreateJob(pb.CreateJobRequest(spec=spec,
                                                     request_id=str(uuid.uuid4()))).name
    if on_created:
        on_created(name)
    arrivals: list[float] = []
    cpu: list[Cpu] = []
    first: float | None = None
    final: pb.Job | None = None
    for event in mc.watch(client, name):
        now = time.perf_counter() - began
        if event.HasField("iteration"):
            arrivals.append(now)
            if server is not None:
                cpu.append(server.cpu())
            first = now if first is None else first
        elif event.job.iteration > 0 and first is None:
            first = now
        if event.HasField("job") and event.job.state in mc.TERMINAL_STATES:
            final = event.job
    wall = time.perf_counter() - began
    if final is None:
        final = client.jobs.GetJob(pb.GetJobRequest(name=name))
    history = list(client.jobs.GetJobHistory(pb.GetJobHistoryRequest(name=name)).iterations)
    return JobRun(final, history, wall, arrivals, first, cpu)


@dataclass
class Together:
    """Jobs started at once and followed to their end: their runs, the wall clock from the
    first CreateJob to the last end, and the daemon's CPU seconds over it."""

    runs: list[JobRun]
    seconds: float
    cpu: Cpu  # spent by the server and the workers

    @property
    def iterations(self) -> int:
        return sum(len(r.history) for r in self.runs)


def run_together(server: Daemon, jobs: Sequence[tuple[mc.Client, pb.JobSpec]],
                 what: str) -> Together:
    """Each (client, spec) started in a thread of its own at once; every job must succeed."""
    runs: list[JobRun] = []
    cpu0, t0 = server.cpu(), time.perf_counter()
    threads = [threading.Thread(target=lambda c=c, s=s: runs.append(run_job(c, s)),
                                daemon=True) for c, s in jobs]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    wall, cpu1 = time.perf_counter() - t0, server.cpu()
    if len(runs) != len(threads):
        raise RuntimeError(f"{what}: a job's watch failed")
    for r in runs:
        require_success(r, what)
    return Together(runs, wall, Cpu(cpu1.server - cpu0.server, cpu1.workers - cpu0.workers))


def require_success(run: JobRun, what: str) -> None:
    if run.job.state != pb.JOB_STATE_SUCCEEDED:
        raise RuntimeError(f"{what}: job {run.job.name} ended "
                           f"{mc.state_name(run.job.state)}: {run.job.error}")


def last_array(client: mc.Client, run: JobRun, folder: Path) -> "np.ndarray":
    """The job's last value of its first parameter, one too large to travel inline (a grid,
    vertex positions): downloaded into ``folder`` and read."""
    import numpy as np
    result = client.jobs.GetJobResult(pb.GetJobResultRequest(name=run.job.name,
                                                             which=pb.WHICH_LAST))
    return np.load(mc.download_blob(client, result.parameters[0].blob,
                                    folder / f"{run.job.name.split('/')[-1]}.npy"))


def wall_spec(scene: pb.Scene, ref_blob: str, *, iterations: int, spp: int,
              schedule: int = pb.SCHEDULE_CONSTANT, seed: int = 0) -> pb.JobSpec:
    """The overhead case's job: the Cornell box's red and green walls from grey, Adam 0.03,
    MSE, no early stop (min_error 0), so every run does exactly ``iterations`` iterations."""
    return pb.JobSpec(scene=scene.name, references=[pb.Reference(blob=ref_blob)],
                      parameters=[pb.ParameterSpec(key=k, initial_value=GREY) for k in WALLS],
                      iterations=iterations, spp=spp, min_error=0.0, learning_rate=0.03,
                      schedule=schedule, loss=pb.LOSS_MSE, seed=seed)


_F = pb.JobSpec.DESCRIPTOR.fields[0]  # a FieldDescriptor, for its type constants
_SCALARS = {_F.TYPE_FLOAT: float, _F.TYPE_DOUBLE: float, _F.TYPE_INT32: int, _F.TYPE_INT64: int,
            _F.TYPE_UINT32: int, _F.TYPE_UINT64: int, _F.TYPE_STRING: str}


def candidate(named: dict[str, str]) -> tuple[dict[str, str], dict[str, object]]:
    """A candidate default's NAME=VALUE pairs as (choices, JobSpec fields): a name that is a
    field of JobSpec (schedule=constant, learning_rate=0.05) sets it, any other names a choice
    (gauss_newton=on). A default on trial may be a setting as well as a choice."""
    fields = pb.JobSpec.DESCRIPTOR.fields_by_name
    choices, spec = {}, {}
    for name, value in named.items():
        field = fields.get(name)
        if field is None:
            choices[name] = value
        elif field.enum_type is not None:
            names = [v.name for v in field.enum_type.values
                     if v.name in (value, value.upper()) or v.name.endswith("_" + value.upper())]
            if len(names) != 1:
                raise ValueError(f"{name}={value}: not one of "
                                 f"{', '.join(v.name for v in field.enum_type.values)}")
            spec[name] = field.enum_type.values_by_name[names[0]].number
        elif field.type in _SCALARS:  # JobSpec's repeated fields are all messages
            spec[name] = _SCALARS[field.type](value)
        else:
            raise ValueError(f"{name}={value}: JobSpec.{name} is not a scalar setting")
    return choices, spec


# ---------------------------------------------------------------------------------------------
# Timing and statistics
# ---------------------------------------------------------------------------------------------


def per_iteration(seconds: Sequence[float]) -> float:
    """Seconds per iteration in steady state: from the end of iteration 0 to the end of the
    last, so the first iteration's kernel compilation and scene load stay out."""
    if len(seconds) < 2:
        return float("nan")
    return (seconds[-1] - seconds[0]) / (len(seconds) - 1)


def alternate(rounds: int, first: Callable[[int], None], second: Callable[[int], None]) -> None:
    """ABBA order: round r runs first-second when r is even, second-first when odd, so slow
    drift of the machine (thermal, other tenants) weighs on both sides alike."""
    for r in range(rounds):
        for fn in ((first, second) if r % 2 == 0 else (second, first)):
            fn(r)


def percentile(values: Sequence[float], p: float) -> float:
    """Linear-interpolated percentile, p in [0, 100]."""
    xs = sorted(values)
    if not xs:
        return float("nan")
    k = (len(xs) - 1) * p / 100
    lo, hi = int(k), min(int(k) + 1, len(xs) - 1)
    return xs[lo] + (xs[hi] - xs[lo]) * (k - lo)


def median(values: Sequence[float]) -> float:
    return statistics.median(values) if values else float("nan")


def spread(values: Sequence[float], fmt: str = "{:.3f}") -> str:
    """"median (min-max, n=N)" of a list of figures."""
    if not values:
        return "n/a"
    return (f"{fmt.format(median(values))} ({fmt.format(min(values))}-"
            f"{fmt.format(max(values))}, n={len(values)})")


def by_method(rows: Sequence[dict], methods: Sequence[str]) -> dict[str, dict[str, list]]:
    """Per method, each column of its rows (one row per seed): method -> column -> values."""
    return {m: {k: [r[k] for r in rows if r["method"] == m] for k in rows[0]} for m in methods}


def write_csv(path: Path, rows: Sequence[dict]) -> Path:
    """Rows of dicts; the columns are the union of their keys in order of appearance."""
    columns: dict[str, None] = {}
    for row in rows:
        columns.update(dict.fromkeys(row))
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as f:
        out = csv.DictWriter(f, list(columns))
        out.writeheader()
        out.writerows({k: _plain(v) for k, v in row.items()} for row in rows)
    return path


def _plain(value: object) -> object:
    return f"{value:.6g}" if isinstance(value, float) else value


def job_series(run: JobRun, label: str) -> report.Series:
    """A daemon job as a report series (errors from the daemon, or from its values)."""
    truth = report.truth_of(run.job.spec)
    return report.Series(run.job.name, label, [report.record_row(r, truth) for r in run.history])


def mib(n: float) -> str:
    return f"{n / 2**20:.1f} MiB"



class Stopped(Exception):
    """The case was told to stop (SIGTERM: its time cap in bench/gpu_run.py). A case that
    catches it reports what it finished; elsewhere it is a failed case, as any error."""

def git_revision() -> str:
    """The commit the run measured, marked dirty when the daemon's code differs from it; on a
    GPU machine, what bench/gpu.sh recorded (MATOPT_BENCH_COMMIT): the copy of the tree there
    may come with the git directory of an older commit."""
    if os.environ.get("MATOPT_BENCH_COMMIT"):  # a copy's git, if any, may be an older one's
        return os.environ["MATOPT_BENCH_COMMIT"]
    try:
        rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, text=True,
                             capture_output=True, timeout=10).stdout.strip()
        if not rev:
            return os.environ.get("MATOPT_BENCH_COMMIT", "unknown")
        dirty = subprocess.run(["git", "status", "--porcelain", "--", "daemon", "proto"],
                               cwd=ROOT, text=True, capture_output=True,
                               timeout=10).stdout.strip()
        return rev + (" (daemon/ or proto/ modified)" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        return os.environ.get("MATOPT_BENCH_COMMIT", "unknown")

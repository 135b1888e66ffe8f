"""The thesis's Tables 2 and 4 on its own scene files (github: sapo17/BachelorThesis, read from
``--thesis-repo DIR``; nothing of it is copied into this repository, which its missing licence
rules out): Mitsuba's plain Adam loop with the thesis's settings against a daemon job with the
daemon's defaults, over several seeds, alternating.

Scenes as shipped, set only through their own ``<default>``s, as a user would: ``integrator``
(Mitsuba 3.9 has no ``prb_reparam``: ``prb`` for Table 2, ``prbvolpath`` for Table 4),
``resx``/``resy`` (the film and its Gaussian filter at the size rendered, so reference and job
blur alike) and nothing else: Table 2's ``max_depth`` stays -1 and Table 4's 64. The reference
is rendered by the daemon at the truth with the scene's own integrator (REF_SPP); both methods
fit that very image.

- Table 2 (``translucent-principled-bsdf/scene-bunny.xml``): truth roughness 0.01, base_color
  (0.412, 0.824, 0.999), spec_trans 0.9, eta 1.49; start 0.5, 0.1 grey, 0.02, 1.54. The plain
  loop has the thesis's settings for it: Adam 0.03, MSE, 16 spp, constant rate.
- Table 4 (``translucent-participating-media/scene-homogeneuous-bunny.xml``): truth alpha
  0.01, albedo (0.412, 0.824, 0.999), sigma_t 0.4, eta 1.49; start 0.98, 0.01 grey, 0.99, 1.55.
  Plain: Adam 0.03, eta's rate 0.003 and eta <= 1.55 (the thesis's), MSE, 8 spp, constant.

Both sides clip to the ranges the daemon lists and to the thesis's eta bound (the daemon's
job is told it too, so that both solve one problem; ``--no-thesis-bounds`` leaves it to the plain
side, as the rows before 2026-12-01 ran). The daemon job sets only the parameters, their starts, the ground truth, the seed, the
iteration count and the plain loop's spp (both sides render the same samples per iteration; the
daemon's default of 16 gave Table 4's defaults twice the plain loop's 8). Where the daemon has
named choices (``Job.choices``), each one in force is also run turned off (``JobSpec.choices``:
NAME "off"), one at a time, and the ``plain`` preset (no choices, constant rate, the plain
loop's rates, spp and bounds) gives the cost of an iteration at equal work: besides its runs in
turn with the plain loop and the defaults for each seed, EQUAL_PAIRS short runs of it and of
the plain loop back to back, alternating, whose median ratio is the figure (the machine's drift
over a table's hour stays out of it). The two draw the same samples (the plain loop is given
the daemon's seed stride), so the pairs also check that the preset is the plain loop: their
errors agree until float sums in another order part them. Table 2 also runs with ``max_depth`` 64 set on the scene,
the depth the daemon used to cap an unbounded one at.

Per run: seconds per iteration (from the end of iteration 0 to the end of the last, so loading
and the first kernels stay out), the time at which every target parameter is within 1% (2%)
of the truth and stays there to the end ("never" when it is not at the end), and the final
relative error of each parameter (rmse / rms(truth); a principled roughness as alpha =
max(0.001, r^2), a microfacet alpha as it is). Per seed and as median (min-max). Per seed
also the plain loop run for as long as the defaults' job ran ("plain, equal time"): the
targets set the defaults against it, so the daemon's extra renders count against it.

Sizes: ``--film``/``--iterations`` (default 683x512 and 150 iterations on a CUDA variant,
128x96 and 100 on the CPU); ``--seeds`` (default 3); ``--tables`` (default both). ``--quick``:
64x48, 20 iterations, one seed, no on/off runs. ``--defaults-only``: the plain loop and the
defaults alone, at the full size.
"""

from __future__ import annotations

import math
import re
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

import common
import plain
from common import Result, Settings, Target
from matopt_client import client as mc
from matopt_api.v1 import matopt_pb2 as pb

# The bench's own daemon renders 1024-spp references at 683x512 in one call.
DAEMON = {"extra": ("--max-samples", str(2**32 - 1))}
REF_SPP = 1024
WARM_UP = 3  # iterations of each side before the runs (kernels compiled, not counted)
# Equal work: the plain loop and the plain preset in short runs back to back, alternating,
# so that the machine's drift over a table's hour stays out of their ratio.
EQUAL_PAIRS, EQUAL_ITERATIONS = 6, 40
NO_REPO = Target("case ran", "skipped: give --thesis-repo DIR (a checkout of "
                 "github.com/sapo17/BachelorThesis)", None)
# The plain preset and the plain loop render the same samples (plain.DAEMON_SEED_STRIDE): their
# errors agree within AGREE for at least AGREE_ITERATIONS (at 128x96, 3 seeds: Table 2 15-31,
# Table 4 23-25; float sums in another order then part them, as two runs of one loop would).
AGREE, AGREE_ITERATIONS = 1e-3, 10
# The plain loop run for as long as the defaults' job (its method name), up to this many
# times the job's iterations.
EQUAL_TIME, EQUAL_TIME_CAP = "plain, equal time", 10


@dataclass(frozen=True)
class Table:
    name: str
    path: str                        # in the thesis's repository
    integrator: str                  # its `$integrator`: what a user sets on Mitsuba 3.9
    truth: dict[str, list[float]]
    start: dict[str, list[float]]
    targets: tuple[str, ...]         # what "within 1% / 2%" is about
    plain_spp: int
    plain_rates: dict[str, float] = field(default_factory=dict)
    plain_max: dict[str, float] = field(default_factory=dict)
    with_depth_64: bool = False      # also run with max_depth 64 set on the scene
    depth: int = -1                  # the scene file's own max_depth (-1: unbounded)
    gate: float = 0.02               # how close ``targets`` must end and stay (defaults_matrix)


B, M = "object_bsdf", "medium1"
BLUE = [0.412, 0.824, 0.999]
TABLES = [
    Table("table2", "scenes/material-preview/translucent-principled-bsdf/scene-bunny.xml", "prb",
          {f"{B}.roughness.value": [0.01], f"{B}.base_color.value": BLUE,
           f"{B}.spec_trans.value": [0.9], f"{B}.eta": [1.49]},
          {f"{B}.roughness.value": [0.5], f"{B}.base_color.value": [0.1] * 3,
           f"{B}.spec_trans.value": [0.02], f"{B}.eta": [1.54]},
          (f"{B}.base_color.value", f"{B}.spec_trans.value", f"{B}.eta"), plain_spp=16,
          with_depth_64=True, gate=0.01),
    Table("table4", "scenes/material-preview/translucent-participating-media/"
          "scene-homogeneuous-bunny.xml", "prbvolpath",
          {f"{B}.alpha.value": [0.01], f"{M}.albedo.value.value": BLUE,
           f"{M}.sigma_t.value.value": [0.4], f"{B}.eta": [1.49]},
          {f"{B}.alpha.value": [0.98], f"{M}.albedo.value.value": [0.01] * 3,
           f"{M}.sigma_t.value.value": [0.99], f"{B}.eta": [1.55]},
          (f"{M}.albedo.value.value", f"{M}.sigma_t.value.value", f"{B}.eta"), plain_spp=8,
          plain_rates={f"{B}.eta": 0.003}, plain_max={f"{B}.eta": 1.55}, depth=64),
]


@dataclass
class Plan:
    film: tuple[int, int]
    iterations: int
    seeds: int
    on_off: bool
    gpu: bool


def plan(settings: Settings, variant: str) -> Plan:
    gpu = variant.startswith("cuda")
    film = settings.film or ((64, 48) if settings.quick else (683, 512) if gpu else (128, 96))
    iterations = settings.iterations or (20 if settings.quick else 150 if gpu else 100)
    seeds = settings.seeds or (1 if settings.quick else 3)
    return Plan(film, iterations, seeds, not (settings.quick or settings.defaults_only), gpu)


# -- errors -----------------------------------------------------------------------------------

def shown(key: str, value) -> np.ndarray:
    """The value compared: a principled roughness as the alpha it shows."""
    v = np.asarray(value, dtype=np.float64)
    return np.maximum(0.001, v * v) if key.endswith("roughness.value") else v


def relative_error(key: str, value, truth) -> float:
    v, t = shown(key, value), shown(key, truth)
    return float(np.sqrt(np.mean((v - t) ** 2)) / np.sqrt(np.mean(t ** 2)))


def time_staying(seconds: list[float], errors: list[dict[str, float]], keys, threshold: float
                 ) -> float | None:
    """The time of the first iteration from which on every key stays within ``threshold``."""
    at = None
    for s, e in zip(seconds, errors):
        if all(e[k] <= threshold for k in keys):
            at = s if at is None else at
        else:
            at = None
    return at


@dataclass
class Run:
    table: str
    method: str
    seed: int
    per_iteration: float
    seconds: list[float]
    errors: list[dict[str, float]]     # per iteration, per key
    iterations: int
    values: dict[str, list[float]]     # at the end
    cpu_per_iteration: float           # CPU seconds (the plain loop's process, the daemon's
                                       # workers): work done, which other tenants disturb less
    notes: list[str] = field(default_factory=list)
    integrator: str = ""
    choices: list = field(default_factory=list)  # pb.Choice of a daemon job
    paths: list[dict[str, list[float]]] = field(default_factory=list)  # values per iteration

    def staying(self, keys, threshold: float) -> float | None:
        return time_staying(self.seconds, self.errors, keys, threshold)

    @property
    def final(self) -> dict[str, float]:
        return self.errors[-1]


# -- the two sides ----------------------------------------------------------------------------

def loadable(xml: Path, repo: Path, out: Path) -> Path:
    """The XML with every file name made absolute (its folder first, then the repository's
    root, as the thesis ran it), Windows separators turned and the ``reparam_*`` properties of
    the removed ``prb_reparam`` dropped (Mitsuba 3.9 refuses them on any other integrator):
    what a user's script on Linux loads. Written to the bench's scratch space, never into this
    repository."""
    text = xml.read_text()

    def absolute(m: re.Match) -> str:
        name = m.group(2).replace("\\", "/")
        found = next((p for p in (xml.parent / name, repo / name) if p.exists()), None)
        return f'{m.group(1)}"{found or name}"'

    text = re.sub(r'(<string\s+name="filename"\s+value=)"([^"]*)"', absolute, text)
    text = re.sub(r'<\w+\s+name="reparam_\w+"[^>]*/>', "", text)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)
    return out


@dataclass
class Prepared:
    table: Table
    scene: pb.Scene
    ref_blob: str
    ref_path: Path
    plain_xml: Path
    overrides: dict[str, str]
    ranges: dict[str, tuple[float, float]]
    thesis_bounds: bool = True  # the daemon's jobs also get the table's plain_max


def prepare(client: mc.Client, table: Table, p: Plan, settings: Settings,
            overrides: dict[str, str] | None = None, reference: tuple[str, Path] | None = None
            ) -> Prepared:
    repo = settings.thesis_repo
    xml = repo / table.path
    sets = {"integrator": table.integrator, "resx": str(p.film[0]), "resy": str(p.film[1]),
            **(overrides or {})}
    main, files = mc.upload_bundle(client, xml, sets, root=repo)
    scene = client.scenes.CreateScene(pb.CreateSceneRequest(
        main_file=main, files=files, overrides=sets, request_id=str(uuid.uuid4())))
    listed = common.parameters(client, scene)
    if reference is None:
        image = client.scenes.RenderScene(pb.RenderSceneRequest(
            name=scene.name, spp=REF_SPP if not settings.quick else 128, sensors=[0], seed=12345,
            parameters=[pb.ParameterValue(key=k, value=v) for k, v in table.truth.items()]
        )).images[0]
        path = settings.work / "references" / f"{table.name}-{image.exr_blob[6:18]}.exr"
        mc.download_blob(client, image.exr_blob, path)
        reference = (image.exr_blob, path)
    ranges = {k: (listed[k].min, table.plain_max.get(k, listed[k].max)) for k in table.start}
    plain_xml = loadable(xml, repo, settings.work / "plain" / f"{table.name}.xml")
    return Prepared(table, scene, reference[0], reference[1], plain_xml, sets, ranges,
                    settings.thesis_bounds)


def run_plain(prep: Prepared, p: Plan, seed: int, variant: str, iterations: int,
              seconds: float = 0.0) -> Run:
    """The plain loop for ``iterations``, or with ``seconds`` for as long as that (the
    daemon's job took: equal time; at most EQUAL_TIME_CAP times the iterations)."""
    t = prep.table
    spec = plain.PlainSpec(prep.plain_xml, prep.ref_path, t.start,
                           iterations * (EQUAL_TIME_CAP if seconds else 1), t.plain_spp,
                           integrator="", overrides=prep.overrides, ranges=prep.ranges,
                           rates=t.plain_rates, seed=seed * plain.DAEMON_SEED_STRIDE,
                           seconds=seconds)
    its = plain.run(spec, variant)
    errors = [{k: relative_error(k, it.values[k], t.truth[k]) for k in t.truth} for it in its]
    times = [it.seconds for it in its]
    return Run(t.name, EQUAL_TIME if seconds else "plain", seed, common.per_iteration(times),
               times, errors, len(its), its[-1].values,
               common.per_iteration([it.cpu for it in its]),
               paths=[{k: np.ravel(v).tolist() for k, v in it.values.items()} for it in its])


def daemon_spec(prep: Prepared, seed: int, iterations: int, choices: dict[str, str] | None = None,
                preset_plain: bool = False) -> pb.JobSpec:
    t = prep.table
    params = []
    for key, start in t.start.items():
        param = pb.ParameterSpec(key=key, initial_value=start)
        if preset_plain:  # the plain loop's rates and bounds: equal work, equal steps
            param.learning_rate = t.plain_rates.get(key, 0.03)
        if key in t.plain_max and (preset_plain or prep.thesis_bounds):
            param.max = t.plain_max[key]
        params.append(param)
    spec = pb.JobSpec(scene=prep.scene.name, references=[pb.Reference(blob=prep.ref_blob)],
                      parameters=params, iterations=iterations, min_error=0.0, seed=seed,
                      spp=t.plain_spp, ground_truth=[pb.ParameterValue(key=k, value=v)
                                                     for k, v in t.truth.items()])
    if preset_plain:
        spec.schedule = pb.SCHEDULE_CONSTANT
        choices = {"all": "off", **(choices or {})}
    choices, fields = common.candidate(choices or {})
    for name, value in fields.items():
        setattr(spec, name, value)
    if choices:
        spec.choices.update(choices)
    return spec


def run_daemon(server: common.Daemon, prep: Prepared, method: str, spec: pb.JobSpec) -> Run:
    t = prep.table
    job = common.run_job(server.client, spec, server=server)
    common.require_success(job, f"real_scenes {t.name} {method} seed {spec.seed}")
    values = [{v.key: list(v.value) for v in r.parameters} for r in job.history]
    errors = [{k: relative_error(k, v[k], t.truth[k]) for k in t.truth if k in v} for v in values]
    return Run(t.name, method, spec.seed, common.per_iteration(job.seconds), job.seconds,
               errors, len(job.history), values[-1], common.per_iteration(job.cpu_workers),
               list(job.job.notes),
               f"{job.job.integrator}: {job.job.integrator_reason}",
               list(getattr(job.job, "choices", [])), values)


def has_choices() -> bool:
    return "choices" in pb.JobSpec.DESCRIPTOR.fields_by_name


# -- the runs ---------------------------------------------------------------------------------

def measure(table: Table, p: Plan, settings: Settings, server: common.Daemon,
            deadline: float = 0.0, runs: list[Run] | None = None) -> list[Run]:
    """The table's runs, appended to ``runs`` as they end (what finished before a stop);
    with a ``deadline`` (epoch seconds), a seed after the first only when the time it took
    fits before it."""
    client, variant = server.client, server.variant
    prep = prepare(client, table, p, settings)
    runs = [] if runs is None else runs
    # Kernels compiled for both sides before anything is timed.
    run_plain(prep, p, 99, variant, WARM_UP)
    run_daemon(server, prep, "warm-up", daemon_spec(prep, 99, WARM_UP))

    def log(run: Run) -> None:
        runs.append(run)
        print(f"bench: real_scenes {run.table} {run.method} seed {run.seed}: "
              f"{run.per_iteration:.3f} s/it, worst final "
              f"{max(run.final[k] for k in table.targets):.4f}", flush=True)

    seeds_began = time.time()

    for seed in range(settings.first_seed, settings.first_seed + p.seeds):
        if seed > settings.first_seed and deadline and time.time() + (time.time() - seeds_began) / (seed - settings.first_seed) > deadline:
            print(f"bench: real_scenes {table.name}: {seed} of {p.seeds} seed(s), the next "
                  "would pass the time cap", flush=True)
            break
        # The plain preset beside them, in turn, for its errors (its cost: equal_work)
        runs_ = [lambda: log(run_plain(prep, p, seed, variant, p.iterations)),
                 lambda: log(run_daemon(server, prep, "daemon", daemon_spec(prep, seed,
                                                                             p.iterations)))]
        if settings.with_choices:
            named = ", ".join(f"{k}={v}" for k, v in settings.with_choices.items())
            runs_.append(lambda: log(run_daemon(
                server, prep, f"daemon, {named}",
                daemon_spec(prep, seed, p.iterations, settings.with_choices))))
        if p.on_off and has_choices():
            runs_.append(lambda: log(run_daemon(
                server, prep, "daemon, plain preset",
                daemon_spec(prep, seed, p.iterations, preset_plain=True))))
        turn = seed % len(runs_)
        for fn in runs_[turn:] + runs_[:turn]:
            fn()
        # Equal time: the plain loop for as long as the defaults' job ran, from its start.
        job = next(r for r in runs if r.method == "daemon" and r.seed == seed)
        log(run_plain(prep, p, seed, variant, p.iterations, seconds=job.seconds[-1]))
    if p.on_off and has_choices():
        names = sorted({c.name for r in runs if r.method == "daemon" for c in r.choices
                        if c.switchable and c.on})
        for name in names:
            for seed in range(settings.first_seed, settings.first_seed + p.seeds):
                log(run_daemon(server, prep, f"daemon, {name} off",
                               daemon_spec(prep, seed, p.iterations, {name: "off"})))
    if p.on_off and has_choices():
        runs += equal_work(server, prep, p)
    if p.on_off and table.with_depth_64:
        deep = prepare(client, table, p, settings, {"max_depth": "64"},
                       (prep.ref_blob, prep.ref_path))
        for seed in range(settings.first_seed, settings.first_seed + p.seeds):
            log(run_daemon(server, deep, "daemon, max_depth 64 set",
                           daemon_spec(deep, seed, p.iterations)))
    return runs


def equal_work(server: common.Daemon, prep: Prepared, p: Plan) -> list[Run]:
    """EQUAL_PAIRS pairs of the plain loop and the plain preset, EQUAL_ITERATIONS each, one
    right after the other in alternating order (seeds 100 on)."""
    out = []
    for k in range(EQUAL_PAIRS):
        pair = [lambda: run_plain(prep, p, 100 + k, server.variant, EQUAL_ITERATIONS),
                lambda: run_daemon(server, prep, "daemon, plain preset", daemon_spec(
                    prep, 100 + k, EQUAL_ITERATIONS, preset_plain=True))]
        for fn in (pair if k % 2 == 0 else pair[::-1]):
            run = fn()
            run.method += " (equal work)"
            out.append(run)
    return out


# -- the report -------------------------------------------------------------------------------

def _short(key: str) -> str:
    name = [x for x in key.split(".") if x != "value"][-1]
    return "alpha (of roughness)" if name == "roughness" else name


def _t(seconds: float | None) -> str:
    return "never" if seconds is None or math.isinf(seconds) else f"{seconds:.1f}"


def _spread_t(values: list[float | None]) -> str:
    xs = [math.inf if v is None else v for v in values]
    return f"{_t(common.median(xs))} ({_t(min(xs))}-{_t(max(xs))})"


def _spread(values: list[float], fmt: str = "{:.4f}") -> str:
    return f"{fmt.format(common.median(values))} ({fmt.format(min(values))}-" \
           f"{fmt.format(max(values))})"


def table_lines(table: Table, p: Plan, runs: list[Run]) -> list[str]:
    keys = list(table.truth)
    methods = list(dict.fromkeys(r.method for r in runs))
    head = ("| method | s / iteration | CPU s / iteration | to 2% staying (s) | to 1% staying (s) "
            "| " + " | ".join(f"final {_short(k)}" for k in keys) + " |")
    out = [head, "|" + "---|" * (5 + len(keys))]
    for m in methods:
        rs = [r for r in runs if r.method == m]
        out.append(f"| {m} | {_spread([r.per_iteration for r in rs], '{:.3f}')} | "
                   f"{_spread([r.cpu_per_iteration for r in rs], '{:.3f}')} | "
                   f"{_spread_t([r.staying(table.targets, 0.02) for r in rs])} | "
                   f"{_spread_t([r.staying(table.targets, 0.01) for r in rs])} | "
                   + " | ".join(_spread([r.final[k] for r in rs]) for k in keys) + " |")
    out += ["", "Per seed:", "", "| method | seed | s / iteration | to 2% | to 1% | "
            + " | ".join(_short(k) for k in keys) + " |", "|" + "---|" * (5 + len(keys))]
    for r in runs:
        out.append(f"| {r.method} | {r.seed} | {r.per_iteration:.3f} | "
                   f"{_t(r.staying(table.targets, 0.02))} | {_t(r.staying(table.targets, 0.01))} "
                   "| " + " | ".join(f"{r.final[k]:.4f}" for k in keys) + " |")
    daemon = next((r for r in runs if r.method == "daemon"), None)
    if daemon is not None:
        out += ["", f"The job's integrator: {daemon.integrator}."]
        for c in daemon.choices:
            out.append(f"- choice `{c.name}` ({'on' if c.on else 'off'}, "
                       f"{c.seconds_per_iteration * 1000:.1f} ms per iteration): {c.why}")
    return out


def targets(table: Table, p: Plan, runs: list[Run]) -> list[Target]:
    def of(method: str) -> list[Run]:
        return [r for r in runs if r.method == method]

    def med_t(rs: list[Run], thr: float) -> float:
        return common.median([math.inf if (t := r.staying(table.targets, thr)) is None else t
                              for r in rs])

    def worst(rs: list[Run]) -> float:
        return common.median([max(r.final[k] for k in table.targets) for r in rs])

    plain_, daemon = of(EQUAL_TIME) or of("plain"), of("daemon")
    keys = ", ".join(_short(k) for k in table.targets)
    out = []
    where = "GPU" if p.gpu else "CPU"
    if table.name == "table2":
        within = 0.01 if p.gpu else 0.02
        d, pl = med_t(daemon, within), med_t(plain_, 0.02)
        bound = 0.5 * pl if p.gpu else pl
        out.append(Target(
            f"{where} {table.name}: {keys} within {within:.0%} staying (daemon, median) against "
            f"{'half ' if p.gpu else ''}the plain loop's time to 2% staying (run as long as the "
            "daemon)",
            f"{_t(d)} s vs {_t(pl)} s", math.isfinite(d) and d < bound))
    else:
        if p.gpu:
            d, pl = med_t(daemon, 0.02), med_t(plain_, 0.02)
            out.append(Target(f"GPU {table.name}: {keys} within 2% staying, daemon vs plain",
                              f"{_t(d)} s vs {_t(pl)} s", math.isfinite(d) and d < pl))
        dw, pw = worst(daemon), worst(plain_)
        out.append(Target(f"{where} {table.name}: worst final error of {keys} (median), daemon "
                          "vs plain at equal time", f"{dw:.4f} vs {pw:.4f}", dw <= pw))
    equal = {r.seed: r for r in of("daemon, plain preset (equal work)")}
    pairs = [(equal[r.seed], r) for r in of("plain (equal work)") if r.seed in equal]
    if pairs:  # per seed: the two ran one after the other
        ratio = common.median([e.per_iteration / q.per_iteration for e, q in pairs])
        cpu = common.median([e.cpu_per_iteration / q.cpu_per_iteration for e, q in pairs])
        out.append(Target(f"{where} {table.name}: time per iteration at equal work (plain "
                          f"preset) / plain loop, median of {len(pairs)} pairs of "
                          f"{EQUAL_ITERATIONS} iterations back to back; CPU time per iteration, "
                          "likewise",
                          f"{ratio:.3f}; CPU {cpu:.3f} (target <= 1.03)", ratio <= 1.03))
        agree = common.median([_agree(e, q) for e, q in pairs])
        out.append(Target(f"{where} {table.name}: the plain preset is the plain loop: same seeds, "
                          "spp and depth, iterations until a component's relative error differs "
                          f"by more than {AGREE} (median of {len(pairs)} pairs; then the order of "
                          "float sums across threads takes over)",
                          f"{agree:.0f} of {EQUAL_ITERATIONS} (target >= {AGREE_ITERATIONS})",
                          agree >= AGREE_ITERATIONS))
    return out


def _agree(a: Run, b: Run) -> int:
    """The iterations from the start at which the two runs' errors agree within AGREE."""
    for i, (x, y) in enumerate(zip(a.errors, b.errors)):
        if any(abs(x[k] - y[k]) > AGREE for k in x):
            return i
    return min(len(a.errors), len(b.errors))


def run(settings: Settings, server: common.Daemon) -> Result:
    result = Result("real_scenes", "The thesis's Tables 2 and 4 on its own scenes")
    if settings.thesis_repo is None:
        result.targets.append(NO_REPO)
        return result
    p = plan(settings, server.variant)
    result.lines.append(
        f"{server.variant}, film {p.film[0]}x{p.film[1]}, {p.iterations} iterations, "
        f"{p.seeds} seed(s); reference {REF_SPP} spp at the truth with the scene's own "
        "integrator and depth. Times are the job's optimizing seconds and the plain loop's "
        "seconds since it began loading; median (min-max) over the seeds.")
    rows = []
    unknown = set(settings.tables) - {t.name for t in TABLES}
    if unknown:
        raise ValueError(f"--tables: no table {', '.join(sorted(unknown))} (there are "
                         f"{', '.join(t.name for t in TABLES)})")
    chosen = [t for t in TABLES if not settings.tables or t.name in settings.tables]
    per_seed = 30.0  # seconds a table's seed took last (with its preparation): a floor
    for k, table in enumerate(chosen):
        began = time.perf_counter()
        # With a time cap (run.py --gpu), each table left gets an equal share of what is left,
        # and one whose first seed would not end before the cap is not begun.
        deadline = (time.time() + (settings.deadline - time.time()) / (len(chosen) - k)
                    if settings.deadline else 0.0)
        if settings.deadline and settings.deadline - time.time() < per_seed:
            result.targets.append(Target(f"{table.name}: ran", "skipped: the time cap", None))
            continue
        runs: list[Run] = []
        try:
            measure(table, p, settings, server, deadline, runs)
            stopped = False
        except common.Stopped:  # the cap came first: the seeds that ended still count
            stopped = True
            ended = {r.seed for r in runs if r.method == EQUAL_TIME}
            runs = [r for r in runs if r.seed in ended]
            result.targets.append(Target(f"{table.name}: stopped", f"at the time cap, "
                                         f"{len(ended)} seed(s) ended before it", None))
            if not runs:
                break
        except Exception as exc:  # noqa: BLE001 - a failed table is a figure too
            result.targets.append(Target(f"{table.name}: ran",
                                         f"FAILED: {type(exc).__name__}: {exc}", False))
            continue
        result.targets += targets(table, p, runs)
        ran = len({r.seed for r in runs if r.method == "daemon"})
        per_seed = max(per_seed, (time.perf_counter() - began) / max(1, ran))
        if ran < p.seeds and not stopped:
            result.targets.append(Target(f"{table.name}: seeds", f"{ran} of {p.seeds}: the "
                                         "next would not have fit the time cap", None))
        result.lines += ["", f"**{table.name}** (`{table.path}`, integrator "
                             f"`{table.integrator}`; plain loop: {table.plain_spp} spp"
                             + (f", rates {table.plain_rates}" if table.plain_rates else "")
                             + (f", maxima {table.plain_max}" if table.plain_max else "")
                             + f"; {time.perf_counter() - began:.0f} s)", ""]
        result.lines += table_lines(table, p, runs)
        for r in runs:
            rows.append({"table": r.table, "method": r.method, "seed": r.seed,
                         "seconds_per_iteration": r.per_iteration,
                         "cpu_per_iteration": r.cpu_per_iteration, "iterations": r.iterations,
                         "to_2pct": r.staying(table.targets, 0.02),
                         "to_1pct": r.staying(table.targets, 0.01),
                         **{f"final:{_short(k)}": v for k, v in r.final.items()},
                         **{f"value:{_short(k)}": " ".join(f"{x:.4g}" for x in v)
                            for k, v in r.values.items()}})
        if stopped:
            break
    if rows:
        result.files.append(common.write_csv(settings.out / "real_scenes.csv", rows))
    return result

"""Memory: the daemon's resident memory over many jobs, to see that it stays flat (no leak).

A daemon of its own (run.py starts one per case) runs small jobs one after the other: first
many on one Cornell box, then one on each of several different scenes (the procedural
principled sphere of tests/scenes.py, each with another base colour: another bundle, preview
render and load, the same kernels). RSS is read after each job, separately for the server
process (gRPC, store, scheduler, watchers) and for the renderer worker (psutil when
installed, else /proc/PID/status). A worker keeps its kernels and at most one preview scene
(dropped when a job starts), and releases each job's scene when the job ends, so its memory
grows over the first jobs (kernels, allocator caches) and should then stay flat; the server
holds no scene at all. What must not happen, in either process, is growth per job or per
scene after that.
"""

from __future__ import annotations

import time

import common
from common import Result, Settings, Target
from matopt_client.cli import report
from matopt_api.v1 import matopt_pb2 as pb
from scenes import PRINCIPLED

RES, ITERATIONS, SPP = 64, 10, 4
SETTLED = 10                # jobs after which memory should be flat
TARGET_MIB_PER_JOB = 0.1    # slope of RSS over the jobs after SETTLED: "flat"
PROCESSES = ("worker", "server")


def slope(xs: list[float], ys: list[float]) -> float:
    """Least-squares slope of ys over xs."""
    n = len(xs)
    mx, my = sum(xs) / n, sum(ys) / n
    var = sum((x - mx) ** 2 for x in xs)
    return sum((x - mx) * (y - my) for x, y in zip(xs, ys)) / var if var else float("nan")


def coloured(n: int) -> str:
    """The principled sphere with its n-th base colour: a different scene each time."""
    old = '<rgb name="base_color" value="0.41, 0.82, 0.99"/>'
    if old not in PRINCIPLED:
        raise RuntimeError("tests/scenes.py PRINCIPLED changed: base_color not found")
    r = 0.05 + (n % 18) * 0.05  # stays in [0.05, 0.9]: Mitsuba refuses reflectances > 1
    return PRINCIPLED.replace(old, f'<rgb name="base_color" value="{r:.2f}, 0.5, '
                                   f'{0.95 - r:.2f}"/>')


def plot(rows: list[dict], path) -> None:
    plt = report.pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(12, 5), dpi=100)
    for ax, process in zip(axes, PROCESSES):
        for series in ("same scene", "different scenes"):
            pts = [(r["jobs_done"], r[f"{process}_rss_mib"]) for r in rows
                   if r["series"] == series]
            ax.plot([p[0] for p in pts], [p[1] for p in pts], marker=".", label=series)
        ax.set_xlabel("jobs finished")
        ax.set_ylabel(f"{process} RSS (MiB)")
        ax.set_title(f"{process} process")
        ax.grid(True, alpha=0.3)
        ax.legend()
    fig.suptitle(f"daemon memory over sequential jobs ({RES}x{RES}, {ITERATIONS} iterations)")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def sample(server: common.Daemon, series: str, jobs_done: int) -> dict:
    server_rss, worker_rss = server.rss()
    return {"series": series, "jobs_done": jobs_done, "worker_rss_mib": worker_rss / 2**20,
            "server_rss_mib": server_rss / 2**20}


def run(settings: Settings, server: common.Daemon) -> Result:
    began = time.perf_counter()
    same, different = (8, 6) if settings.quick else (50, 30)
    client = server.client  # a daemon started for this case: nothing loaded before
    rows: list[dict] = [sample(server, "start", 0)]
    scene = common.cornell(client, RES)
    ref_blob, _ = common.reference(client, scene, 64, settings.work)
    spec = common.wall_spec(scene, ref_blob, iterations=ITERATIONS, spp=SPP)
    for n in range(1, same + 1):
        common.require_success(common.run_job(client, spec), "memory")
        rows.append(sample(server, "same scene", n))
    before_scenes = dict(rows[-1])
    key = "shape_2.bsdf.base_color.value"
    for n in range(1, different + 1):
        other = common.xml_scene(client, settings.work, coloured(n), f"sphere{n}",
                                 resx=RES, resy=RES)
        blob, _ = common.reference(client, other, 16, settings.work)
        job = pb.JobSpec(scene=other.name, references=[pb.Reference(blob=blob)],
                         parameters=[pb.ParameterSpec(key=key, initial_value=[0.5] * 3)],
                         iterations=ITERATIONS, spp=SPP, min_error=0.0)
        common.require_success(common.run_job(client, job), "memory")
        rows.append(sample(server, "different scenes", same + n))

    same_rows = [r for r in rows if r["series"] == "same scene"]
    first = min(SETTLED, same // 2)
    settled = [r for r in same_rows if r["jobs_done"] >= first]
    scene_rows = [r for r in rows if r["series"] == "different scenes"]
    half = different // 2  # the first scenes fill the allocator's caches
    late = scene_rows[half:]
    targets, lines = [], [f"Jobs: {ITERATIONS} iterations, {RES}x{RES}, {SPP} spp, one after "
                          "the other."]
    for process in PROCESSES:
        column = f"{process}_rss_mib"
        per_job = slope([r["jobs_done"] for r in settled], [r[column] for r in settled])
        per_scene = slope([r["jobs_done"] for r in late], [r[column] for r in late])
        targets += [
            Target(f"{process} RSS growth per job from job {first} to {same} (same scene)",
                   f"{per_job * 1024:.0f} KiB/job (target <= {TARGET_MIB_PER_JOB * 1024:.0f} "
                   "KiB/job)", per_job <= TARGET_MIB_PER_JOB),
            Target(f"{process} RSS growth per scene from scene {half + 1} to {different} (a "
                   "new scene each job)", f"{per_scene * 1024:.0f} KiB/scene (target <= "
                   f"{TARGET_MIB_PER_JOB * 1024:.0f} KiB/scene)",
                   per_scene <= TARGET_MIB_PER_JOB)]
        rss = {r["jobs_done"]: r[column] for r in same_rows}
        marks = [n for n in (1, 10, 50) if n in rss]
        lines += [
            f"- {process}: RSS at start {rows[0][column]:.0f} MiB; after "
            + ", ".join(f"{n} job(s) {rss[n]:.0f} MiB" for n in marks) + " on the same scene; "
            f"then {different} different scenes: {before_scenes[column]:.0f} -> "
            f"{rows[-1][column]:.0f} MiB "
            f"({scene_rows[half - 1][column] - before_scenes[column]:+.0f} MiB over the first "
            f"{half}, then {per_scene * 1024:.0f} KiB per scene)"]
    csv = common.write_csv(settings.out / "memory.csv", rows)
    png = settings.out / "memory.png"
    plot(rows, png)
    return Result("memory", "Daemon memory over many jobs", targets, lines, [csv, png],
                  time.perf_counter() - began)

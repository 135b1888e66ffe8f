"""Live scenes: does a job get slower when the daemon holds other scenes in memory?

Mitsuba traces a virtual call (a BSDF's, an emitter's) over every live instance of that class
in the process, not only over the rendered scene's, so each scene a process keeps loaded can
make every render's kernels bigger. The daemon keeps the last 4 scenes it rendered (previews,
references) loaded for further renders, and each running or paused job holds its own. This
case runs the same small job (the principled sphere of tests/scenes.py, 48x48, where fixed
costs per iteration show) with no other scene held, and right after 4 other scenes were
rendered (so they sit in the daemon's scene cache), alternating; DeleteScene drops them from
the cache between rounds. Reported: seconds and daemon CPU per iteration, held / not held.
No target: this is a finding of the benchmark run, kept so that a fix can be measured.
"""

from __future__ import annotations

import time

import common
from common import Result, Settings, Target
from matopt_api.v1 import matopt_pb2 as pb
from scenes import PRINCIPLED

OTHERS = 4  # matoptd's scheduler.SCENE_CACHE
KEYS = ["shape_2.bsdf.base_color.value", "shape_2.bsdf.spec_trans.value"]


def run(settings: Settings, server: common.Daemon) -> Result:
    began = time.perf_counter()
    iterations, rounds = (10, 2) if settings.quick else (30, 4)
    client = server.client
    scene = common.xml_scene(client, settings.work, PRINCIPLED, "sphere")
    ref_blob, _ = common.reference(client, scene, 64, settings.work)
    spec = pb.JobSpec(scene=scene.name, references=[pb.Reference(blob=ref_blob)],
                      parameters=[pb.ParameterSpec(key=k) for k in KEYS],
                      iterations=iterations, spp=4, min_error=0.0)
    rows: list[dict] = []
    figures: dict[str, list[tuple[float, float]]] = {"none": [], "held": []}

    def job(held: str) -> None:
        run_ = common.run_job(client, spec, pid=server.pid)
        common.require_success(run_, "live_scenes")
        s, c = common.per_iteration(run_.seconds), common.per_iteration(run_.cpu)
        figures[held].append((s, c))
        rows.append({"other_scenes_held": held, "seconds_per_iteration": s,
                     "daemon_cpu_seconds_per_iteration": c})

    def alone(r: int) -> None:
        job("none")

    def beside_others(r: int) -> None:
        others = [common.cornell(client, 64 + 8 * n) for n in range(OTHERS)]
        for other in others:  # a preview render loads each into the daemon's scene cache
            client.scenes.RenderScene(pb.RenderSceneRequest(name=other.name, spp=1))
        try:
            job("held")
        finally:
            for other in others:  # DeleteScene also drops it from the cache
                client.scenes.DeleteScene(pb.DeleteSceneRequest(name=other.name))

    job("none")  # warm-up: kernels compiled; not counted
    figures["none"].clear()
    rows.clear()
    common.alternate(rounds, alone, beside_others)
    time_ratio = common.median([h[0] / n[0] for n, h in zip(figures["none"], figures["held"])])
    cpu_ratio = common.median([h[1] / n[1] for n, h in zip(figures["none"], figures["held"])])
    csv = common.write_csv(settings.out / "live_scenes.csv", rows)
    return Result("live_scenes", "Other scenes held by the daemon", [
        Target(f"per-iteration time with {OTHERS} other scenes in the daemon's cache / none "
               "(finding; no target)", f"time {time_ratio:.2f}x, daemon CPU {cpu_ratio:.2f}x",
               None),
    ], [
        f"Job: principled sphere, 48x48, 4 spp, {iterations} iterations, 2 parameters; "
        f"{rounds} alternating rounds. The other scenes are Cornell boxes rendered once at "
        "1 spp just before the job.",
        "- per iteration with none held: "
        f"{common.spread([n[0] * 1000 for n in figures['none']], '{:.0f}')} ms (CPU "
        f"{common.spread([n[1] * 1000 for n in figures['none']], '{:.0f}')} ms); with "
        f"{OTHERS} held: {common.spread([h[0] * 1000 for h in figures['held']], '{:.0f}')} ms "
        f"(CPU {common.spread([h[1] * 1000 for h in figures['held']], '{:.0f}')} ms)",
    ], [csv], time.perf_counter() - began)

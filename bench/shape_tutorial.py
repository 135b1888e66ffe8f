"""Mitsuba's own shape tutorial as a job: the daemon's defaults against the tutorial's loops.

``inverse_rendering/shape_optimization.ipynb`` of mitsuba-tutorials (``--tutorials-repo``, a
checkout; its meshes and environment map are read from there, never committed): a diffuse
sphere (scenes/meshes/ico_10k.ply) pulled toward Suzanne (suzanne.ply), seen by 8 cameras on
a golden-ratio spiral at distance 5 (fov 45) under envmap2.exr, rendered by
``direct_projective`` with ``sppi`` 0. References of Suzanne at 256 spp (the tutorial's). The
notebook's two loops make a step per camera in turn:
- ``tutorial, naive``: Adam 0.03 on the vertex positions, L2 loss;
- ``tutorial, large steps``: LargeSteps with lambda 25, uniform Adam 0.1 on its differential
  coordinates, L1 loss.
The notebook runs at 256x256 and 128 spp for 100 iterations, hours on 2 CPU cores; here both
sides render RES x RES at SPP for ITERATIONS (the same samples per step).

Per seed, five runs: the two loops (bench process, Mitsuba directly); the daemon given the
large-steps loop's settings (lambda, rate, L1 loss, constant rate: conformance); ``daemon``,
the defaults given only the parameter and the notebook's camera order (``sensor_mode``
step_per_sensor); and the large-steps loop again for as long as the defaults' job optimized.
Reported: the Chamfer distance of the vertices to Suzanne's (the mean distance to the nearest
vertex of the other mesh, both ways, halved), the seconds taken (median and spread over the
seeds). Target: the defaults' distance no worse than the large-steps loop's at equal time.
"""

from __future__ import annotations

import math
import shutil
import time
from pathlib import Path

import numpy as np

import common
import plain
from common import Result, Settings, Target
from matopt_api.v1 import matopt_pb2 as pb

RES, VIEWS, SPP, REF_SPP, ITERATIONS, SEEDS = 32, 8, 16, 256, 12, (0, 1, 2)
NAIVE_RATE, LARGE_RATE, LAMBDA = 0.03, 0.1, 25.0  # the notebook's
KEY = "shape.vertex_positions"
MESHES, ENVMAP = "scenes/meshes", "scenes/textures/envmap2.exr"
START, TRUTH = "ico_10k.ply", "suzanne.ply"
EQUAL_TIME = "tutorial, large steps, equal time"
EQUAL_TIME_CAP = 10


def _sensors() -> str:
    """The notebook's cameras: on a golden-ratio spiral around the origin."""
    golden = (1 + 5 ** 0.5) / 2
    out = []
    for i in range(VIEWS):
        theta, phi = 2 * math.pi * i / golden, math.acos(1 - 2 * (i + 0.5) / VIEWS)
        o = [5 * math.cos(theta) * math.sin(phi), 5 * math.sin(theta) * math.sin(phi),
             5 * math.cos(phi)]
        out.append(f"""
    <sensor type="perspective"><float name="fov" value="45"/>
        <transform name="to_world"><lookat origin="{o[0]:.6f}, {o[1]:.6f}, {o[2]:.6f}"
            target="0, 0, 0" up="0, 1, 0"/></transform>
        <film type="hdrfilm"><integer name="width" value="{RES}"/>
            <integer name="height" value="{RES}"/><rfilter type="gaussian"/>
            <boolean name="sample_border" value="true"/></film>
        <sampler type="independent"><integer name="sample_count" value="{SPP}"/></sampler>
    </sensor>""")
    return "".join(out)


def scene_xml(mesh: str) -> str:
    return f"""<scene version="3.0.0">
    <integrator type="direct_projective"><integer name="sppi" value="0"/></integrator>
    {_sensors()}
    <emitter type="envmap"><string name="filename" value="envmap2.exr"/></emitter>
    <shape type="ply" id="shape">
        <string name="filename" value="{mesh}"/>
        <bsdf type="diffuse"/>
    </shape>
</scene>
"""


def chamfer(a: np.ndarray, b: np.ndarray) -> float:
    """Symmetric Chamfer distance of two vertex sets, in blocks (bounded memory)."""
    def nearest(p: np.ndarray, q: np.ndarray) -> float:
        return float(np.concatenate([np.sqrt(((p[i:i + 64, None] - q[None]) ** 2).sum(-1))
                                     .min(axis=1) for i in range(0, len(p), 64)]).mean())
    return (nearest(a, b) + nearest(b, a)) / 2


def tutorial_loop(xml: Path, references: dict[int, Path], seed: int, variant: str, large: bool,
                  seconds: float = 0.0) -> tuple[np.ndarray, float, int]:
    """One of the notebook's loops as it is written; with ``seconds``, iterations until that
    much time has passed (at most EQUAL_TIME_CAP times as many). The vertices, the seconds
    taken (scene load in, as a job's) and the iterations."""
    mi = plain.mitsuba(variant)
    import drjit as dr

    began = time.perf_counter()
    scene = mi.load_file(str(xml))
    refs = plain.read_references(mi, references)
    params = mi.traverse(scene)
    if large:
        steps = mi.ad.LargeSteps(params[KEY], params["shape.faces"], LAMBDA)
        opt = mi.ad.Adam(lr=LARGE_RATE, uniform=True)
        opt["u"] = steps.to_differential(params[KEY])
    else:
        opt = mi.ad.Adam(lr=NAIVE_RATE)
        opt[KEY] = params[KEY]
    sensors = scene.sensors()
    done = 0
    for it in plain.iterations(ITERATIONS, began, seconds, EQUAL_TIME_CAP):
        for s in range(VIEWS):
            if large:
                params[KEY] = steps.from_differential(opt["u"])
                params.update()
            else:
                params.update(opt)
            image = mi.render(scene, params, sensor=sensors[s], spp=SPP, seed=seed * 1000 + it)
            diff = image - refs[s]
            loss = dr.mean(dr.abs(diff) if large else dr.square(diff), axis=None)
            dr.backward(loss)
            opt.step()
        done = it + 1
    last = steps.from_differential(opt["u"]) if large else opt[KEY]
    return np.array(last, dtype=np.float32).reshape(-1, 3), time.perf_counter() - began, done


def run(settings: Settings, server: common.Daemon) -> Result:
    began = time.perf_counter()
    repo = settings.tutorials_repo
    title = "Mitsuba's shape tutorial"
    if repo is None or not (repo / MESHES / TRUTH).exists():
        return Result("shape_tutorial", title, [], lines=[
            f"Skipped: no mitsuba-tutorials checkout with {MESHES}/{TRUTH} "
            "(`--tutorials-repo DIR`)."])
    client = server.client
    seeds = SEEDS[:1] if settings.quick else SEEDS
    folder = settings.work / "shape_tutorial"
    folder.mkdir(parents=True, exist_ok=True)
    for name in (START, TRUTH):
        shutil.copyfile(repo / MESHES / name, folder / name)
    shutil.copyfile(repo / ENVMAP, folder / "envmap2.exr")
    (folder / "reference.xml").write_text(scene_xml(TRUTH))
    xml = folder / "job.xml"
    xml.write_text(scene_xml(START))

    refs, paths = common.every_reference(client, folder / "reference.xml", REF_SPP)
    scene = common.bundle_scene(client, xml)

    def daemon(seed: int, notebook: bool = False) -> tuple[np.ndarray, float, int]:
        param = pb.ParameterSpec(key=KEY, learning_rate=LARGE_RATE if notebook else None)
        spec = pb.JobSpec(scene=scene.name, iterations=ITERATIONS, spp=SPP, min_error=0.0,
                          seed=seed, sensor_mode=pb.SENSOR_MODE_STEP_PER_SENSOR,
                          parameters=[param], references=[
                              pb.Reference(blob=r.exr_blob, sensor=r.sensor) for r in refs])
        if notebook:  # the large-steps loop's settings: its lambda, rate, L1 loss, no decay
            spec.large_steps_lambda, spec.loss = LAMBDA, pb.LOSS_MAE
            spec.schedule = pb.SCHEDULE_CONSTANT
        done = common.run_job(client, spec)
        common.require_success(done, "shape_tutorial")
        got = common.last_array(client, done, folder).reshape(-1, 3)
        return got, done.history[-1].seconds, len(done.history)

    methods = {
        "tutorial, naive": lambda s: tutorial_loop(xml, paths, s, server.variant, False),
        "tutorial, large steps": lambda s: tutorial_loop(xml, paths, s, server.variant, True),
        "daemon, the notebook's settings": lambda s: daemon(s, True),
        "daemon": daemon,
        EQUAL_TIME: lambda s: tutorial_loop(xml, paths, s, server.variant, True,
                                            rows[-1]["seconds"])}
    start = _vertices(folder / START, server.variant)
    truth = _vertices(folder / TRUTH, server.variant)
    rows: list[dict] = []
    for seed in seeds:
        for name, fn in methods.items():
            got, seconds, iterations = fn(seed)
            rows.append({"seed": seed, "method": name, "seconds": seconds,
                         "iterations": iterations, "chamfer": chamfer(got, truth)})
            print(f"bench: shape_tutorial seed {seed} {name}: Chamfer {rows[-1]['chamfer']:.4f}"
                  f" in {seconds:.1f} s ({iterations} iterations)", flush=True)
    csv = common.write_csv(settings.out / "shape_tutorial.csv", rows)
    of = common.by_method(rows, list(methods))
    dist = {n: of[n]["chamfer"] for n in methods}
    met = common.median(dist["daemon"]) <= common.median(dist[EQUAL_TIME])
    lines = [f"{len(seeds)} seed(s), {ITERATIONS} iterations x {VIEWS} cameras at {SPP} spp, "
             f"{RES}x{RES}; {len(start)} vertices from the sphere, Suzanne's {len(truth)}; the "
             f"start's Chamfer distance {chamfer(start, truth):.4f}. Seconds: optimizing "
             "time (a job's to its last iteration, a loop's with its scene load). "
             f"{time.perf_counter() - began:.0f} s in all.", "",
             "| method | Chamfer distance at the end | iterations | seconds |",
             "|---|---|---|---|"]
    lines += [f"| {n} | {common.spread(dist[n], '{:.4f}')} "
              f"| {common.median(of[n]['iterations']):.0f} "
              f"| {common.spread(of[n]['seconds'], '{:.1f}')} |" for n in methods]
    return Result("shape_tutorial", title, [
        Target("Mitsuba's shape tutorial (ico_10k toward Suzanne): Chamfer distance at the "
               "end, the daemon's defaults vs the tutorial's large-steps loop at equal time "
               "(median over seeds)",
               f"{common.median(dist['daemon']):.4f} vs {common.median(dist[EQUAL_TIME]):.4f} "
               f"(its {ITERATIONS} iterations: {common.median(dist['tutorial, large steps']):.4f};"
               f" naive: {common.median(dist['tutorial, naive']):.4f})", met),
    ], lines=lines, files=[csv])


def _vertices(path: Path, variant: str) -> np.ndarray:
    mi = plain.mitsuba(variant)
    mesh = mi.load_dict({"type": "ply", "filename": str(path)})
    return np.array(mi.traverse(mesh)["vertex_positions"], np.float32).reshape(-1, 3)

"""Geometry: what optimizing vertex positions costs, against a material on the same scene.

Vertex positions move visibility edges, so the daemon renders them with a projective
integrator (direct_projective for this direct-light scene), far costlier per iteration than
prb. The case runs the quad of tests/scenes.py QUAD_IN_FRONT (16x16, 8 spp), once recovering
its reflectance (prb) and once its vertex positions from a (0.2, 0.1) shift, alternating, and
reports seconds per iteration of each, their ratio, and how far the quad's centre ended from
the truth in the image plane. This is the benchmark behind the `slow` test of the same job.

Then the scene's own integrator, as Mitsuba's shape example sets it: a sphere of 642
vertices pulled toward a box-like target (tests/scenes.py mesh_in_views) in 8 views at 24x24,
rendered by the scene's ``direct_projective`` with ``sppi`` 0 (no indirect silhouettes), its
vertex positions optimized by the daemon and by bench/plain.py's loop with the scene's
integrator (both plain Adam 0.01, large steps off, constant rate, 8 spp, the same
references), alternating; the target is the daemon's seconds per step within 1.1x of the
loop's. (Replaced by a default
direct_projective, sppi = spp, such a step took 38-51x the loop's.)
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

import common
import plain
from common import Result, Settings, Target
from matopt_client import client as mc
from matopt_api.v1 import matopt_pb2 as pb
from scenes import (QUAD_CORNERS, QUAD_IN_FRONT, box_like, chamfer, icosphere, mesh_in_views,
                    mesh_ply, quad_obj)

KEY = "quad.vertex_positions"
COLOUR = "quad.bsdf.reflectance.value"
OWN_RES, OWN_VIEWS, OWN_TARGET = 24, 8, 1.1  # the scene's own integrator; daemon / loop
LARGE_ITERATIONS = 60
BLOB = "blob.vertex_positions"


def run(settings: Settings, server: common.Daemon) -> Result:
    began = time.perf_counter()
    iterations = 6 if settings.quick else 30
    client = server.client
    work = settings.work / "geometry"
    work.mkdir(parents=True, exist_ok=True)
    (work / "quad.obj").write_bytes(quad_obj())
    (work / "quad.xml").write_text(QUAD_IN_FRONT)
    scene = common.bundle_scene(client, work / "quad.xml")
    ref_blob, _ = common.reference(client, scene, 128, work)
    truth = np.array(QUAD_CORNERS, dtype=np.float32)
    base = dict(scene=scene.name, references=[pb.Reference(blob=ref_blob)],
                iterations=iterations, spp=8, min_error=0.0)
    geometry = pb.JobSpec(**base, parameters=[pb.ParameterSpec(
        key=KEY, learning_rate=0.02, initial_value=(truth + [0.2, 0.1, 0]).ravel().tolist())])
    material = pb.JobSpec(**base, parameters=[pb.ParameterSpec(
        key=COLOUR, initial_value=[0.5, 0.5, 0.5])])
    runs: dict[str, list] = {"material": [], "geometry": []}
    common.alternate(1 if settings.quick else 2,
                     lambda _: runs["material"].append(common.run_job(client, material)),
                     lambda _: runs["geometry"].append(common.run_job(client, geometry)))
    for name, rs in runs.items():
        for r in rs:
            common.require_success(r, f"geometry {name}")
    per = {name: common.median([common.per_iteration(r.seconds) for r in rs])
           for name, rs in runs.items()}
    last = runs["geometry"][-1]
    centre = np.array(last.history[-1].parameters[0].value).reshape(-1, 3).mean(axis=0)
    rows = [{"job": name, "integrator": rs[-1].job.integrator,
             "seconds_per_iteration": per[name]} for name, rs in runs.items()]
    own, own_rows, own_lines = scene_integrator(settings, server, work, iterations)
    large, large_rows, large_line = large_steps(settings, server, work)
    csv = common.write_csv(settings.out / "geometry.csv", rows + own_rows + large_rows)
    ratio = per["geometry"] / per["material"]
    return Result("geometry", "Geometry (vertex positions, projective integrator)", [
        Target("seconds per iteration, vertex positions / reflectance",
               f"{ratio:.1f}x ({per['geometry']:.2f} s vs {per['material']:.3f} s, "
               f"{runs['geometry'][-1].job.integrator} vs {runs['material'][-1].job.integrator})",
               None),
        Target("quad centre error in the image plane after the run",
               f"{np.abs(centre[:2]).max():.3f} (start 0.2)", None),
        own,
        large,
    ], lines=[f"{iterations} iterations at 16x16, 8 spp; {time.perf_counter() - began:.0f} s",
              *(line for own_line in [*own_lines, large_line] for line in ("", own_line))],
        files=[csv])


def blob_scene(client: mc.Client, work: Path, name: str, level: int = 3
               ) -> tuple[Path, Path, pb.Scene, list[pb.Image]]:
    """The box-like target (a sphere of icosphere(level) pushed toward a cube) in OWN_VIEWS
    views, and its references at 64 spp: (folder, scene file, scene, references)."""
    folder = work / name
    folder.mkdir(exist_ok=True)
    sphere, faces = icosphere(level)
    (folder / "blob.ply").write_bytes(mesh_ply(box_like(sphere), faces))
    xml = folder / "blob.xml"
    xml.write_text(mesh_in_views(OWN_RES, OWN_VIEWS))
    scene = common.bundle_scene(client, xml)
    refs = client.scenes.RenderScene(pb.RenderSceneRequest(name=scene.name, spp=64,
                                                           seed=12345)).images
    return folder, xml, scene, list(refs)


def large_steps(settings: Settings, server: common.Daemon, work: Path
                ) -> tuple[Target, list[dict], str]:
    """The default large steps (lambda and rate from the mesh) against plain Adam (the choice
    off, rate 0.01: the better of 0.01 and 0.03 in every trial) on the box-like target at 162
    and 2562 vertices, Chamfer distance after LARGE_ITERATIONS, over seeds."""
    client = server.client
    seeds = range(1 if settings.quick else 3)
    rows: list[dict] = []
    met, said = True, []
    for level in (2, 4):
        folder, _, scene, refs = blob_scene(client, work, f"large{level}", level)
        sphere, faces = icosphere(level)
        ends: dict[str, list[float]] = {"default": [], "plain": []}
        for seed in seeds:
            for name, extra in (("default", {}), ("plain", {"learning_rate": 0.01})):
                spec = pb.JobSpec(
                    scene=scene.name, iterations=LARGE_ITERATIONS, spp=4, min_error=0.0,
                    seed=seed, references=[pb.Reference(blob=r.exr_blob, sensor=r.sensor)
                                           for r in refs],
                    parameters=[pb.ParameterSpec(key=BLOB, **extra, initial_value=(
                        0.7 * sphere).ravel().tolist())],
                    choices={} if name == "default" else {"large_steps": "off"})
                run_ = common.run_job(client, spec)
                common.require_success(run_, f"geometry, large steps {name}")
                got = common.last_array(client, run_, folder).reshape(-1, 3)
                ends[name].append(chamfer(got, box_like(sphere), faces))
                rows.append({"job": f"large steps: {name}", "vertices": len(sphere),
                             "seed": seed, "chamfer": ends[name][-1]})
        met &= common.median(ends["default"]) < common.median(ends["plain"])
        said.append(f"{len(sphere)} vertices {common.spread(ends['default'])} against "
                    f"{common.spread(ends['plain'])}")
    sphere, faces = icosphere(2)
    start = chamfer(0.7 * sphere, box_like(sphere), faces)
    return (Target("Chamfer distance to the box-like target, default large steps against "
                   "plain Adam (median of seeds; the default lower)", "; ".join(said), met),
            rows, f"Large steps by default: {OWN_VIEWS} views at {OWN_RES}x{OWN_RES}, 4 spp, "
                  f"{LARGE_ITERATIONS} iterations, {len(seeds)} seed(s); the start's Chamfer "
                  f"distance about {start:.3f}")


def scene_integrator(settings: Settings, server: common.Daemon, work: Path,
                     iterations: int) -> tuple[Target, list[dict], list[str]]:
    """The daemon's seconds per step against Mitsuba's loop, both with the scene's
    direct_projective at sppi 0."""
    client = server.client
    folder, xml, scene, refs = blob_scene(client, work, "blob")
    paths = {}
    for image in refs:
        paths[image.sensor] = folder / f"ref{image.sensor}.exr"
        mc.download_blob(client, image.exr_blob, paths[image.sensor])
    sphere, _ = icosphere(3)
    start = (0.7 * sphere).ravel().tolist()
    spec = pb.JobSpec(scene=scene.name, iterations=iterations, spp=8, min_error=0.0,
                      loss=pb.LOSS_MSE, schedule=pb.SCHEDULE_CONSTANT,
                      references=[pb.Reference(blob=r.exr_blob, sensor=r.sensor) for r in refs],
                      parameters=[pb.ParameterSpec(key=BLOB, learning_rate=0.01,
                                                   initial_value=start)],
                      choices={"large_steps": "off"})  # the plain loop's steps: equal work
    loop = plain.PlainSpec(xml, paths[0], {BLOB: start}, iterations, 8, integrator="",
                           ranges={BLOB: (-10.0, 10.0)}, rate=0.01,
                           more_references={s: p for s, p in paths.items() if s})
    per: dict[str, list[float]] = {"daemon": [], "plain": []}
    rows: list[dict] = []
    reasons: set[str] = set()

    def daemon(r: int) -> None:
        run_ = common.run_job(client, spec)
        common.require_success(run_, "geometry, the scene's integrator")
        reasons.add(f"{run_.job.integrator}: {run_.job.integrator_reason}")
        per["daemon"].append(common.per_iteration(run_.seconds))
        rows.append({"job": "scene's integrator, daemon", "integrator": run_.job.integrator,
                     "seconds_per_iteration": per["daemon"][-1], "round": r})

    def mitsuba(r: int) -> None:
        its = plain.run(loop, server.variant)
        per["plain"].append(common.per_iteration([it.seconds for it in its]))
        rows.append({"job": "scene's integrator, plain loop", "integrator": "direct_projective",
                     "seconds_per_iteration": per["plain"][-1], "round": r})

    daemon(-1)  # warm-up: compiles kernels on both sides; not counted
    mitsuba(-1)
    per["daemon"].clear()
    per["plain"].clear()
    common.alternate(1 if settings.quick else 3, daemon, mitsuba)
    ratios = [d / p for d, p in zip(per["daemon"], per["plain"])]
    ratio = common.median(ratios)
    target = Target(f"seconds per step, the scene's direct_projective sppi 0, daemon / "
                    f"Mitsuba's loop (<= {OWN_TARGET}x)",
                    f"{ratio:.2f}x ({common.spread(per['daemon'])} s vs "
                    f"{common.spread(per['plain'])} s)", ratio <= OWN_TARGET)
    lines = [f"The scene's integrator: a sphere of {len(sphere)} vertices toward a box-like "
             f"target, {OWN_VIEWS} views at {OWN_RES}x{OWN_RES}, 8 spp, {iterations} "
             "iterations, the scene's direct_projective with sppi 0, after a warm-up of each; "
             "ratio per round " + ", ".join(f"{r:.3f}" for r in ratios),
             "The daemon's integrator: " + "; ".join(sorted(reasons))]
    return target, rows, lines

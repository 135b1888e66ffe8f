"""Geometry: what optimizing vertex positions costs, against a material on the same scene.

Vertex positions move visibility edges, so the daemon renders them with a projective
integrator (direct_projective for this direct-light scene), far costlier per iteration than
prb. The case runs the quad of tests/scenes.py QUAD_IN_FRONT (16x16, 8 spp), once recovering
its reflectance (prb) and once its vertex positions from a (0.2, 0.1) shift, alternating, and
reports seconds per iteration of each, their ratio, and how far the quad's centre ended from
the truth in the image plane. This is the benchmark behind the `slow` test of the same job.
"""

from __future__ import annotations

import time

import numpy as np

import common
from common import Result, Settings, Target
from matopt_client import client as mc
from matopt_api.v1 import matopt_pb2 as pb
from scenes import QUAD_CORNERS, QUAD_IN_FRONT, quad_obj

KEY = "quad.vertex_positions"
COLOUR = "quad.bsdf.reflectance.value"


def run(settings: Settings, server: common.Daemon) -> Result:
    began = time.perf_counter()
    iterations = 6 if settings.quick else 30
    client = server.client
    work = settings.work / "geometry"
    work.mkdir(parents=True, exist_ok=True)
    (work / "quad.obj").write_bytes(quad_obj())
    (work / "quad.xml").write_text(QUAD_IN_FRONT)
    main, files = mc.upload_bundle(client, work / "quad.xml")
    scene = client.scenes.CreateScene(pb.CreateSceneRequest(main_file=main, files=files))
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
    csv = common.write_csv(settings.out / "geometry.csv", rows)
    ratio = per["geometry"] / per["material"]
    return Result("geometry", "Geometry (vertex positions, projective integrator)", [
        Target("seconds per iteration, vertex positions / reflectance",
               f"{ratio:.1f}x ({per['geometry']:.2f} s vs {per['material']:.3f} s, "
               f"{runs['geometry'][-1].job.integrator} vs {runs['material'][-1].job.integrator})",
               None),
        Target("quad centre error in the image plane after the run",
               f"{np.abs(centre[:2]).max():.3f} (start 0.2)", None),
    ], lines=[f"{iterations} iterations at 16x16, 8 spp; {time.perf_counter() - began:.0f} s"],
        files=[csv])

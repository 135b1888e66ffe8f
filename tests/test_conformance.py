"""The ``plain`` preset is Mitsuba's plain Adam loop: a job with every choice off, a constant
schedule and one learning rate follows the same trajectories as the loop of Mitsuba's own
tutorial (bench/plain.py, run in a process of its own) on the same scene, reference and
starts, within the noise of the seeds, on a surface, a medium, a texture and a grid.

Both render iteration i with the same seed (the daemon's base seed s gives iteration i the seed
s * 1000003 + i per sensor slot, which the plain loop is given), so what is left between them is
the order of float sums across threads, which on the LLVM backend varies from run to run.
Trajectories are compared over 3 seeds: at every iteration, per component, the two means may
differ by no more than the seeds' own spread allows (SPREADS standard errors) plus a small
absolute tolerance for components that hardly vary.
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from matopt_api.v1 import matopt_pb2 as pb

from conftest import ROOT, wait_state
from scenes import create_scene, exr, grid_volume, medium_sphere, textured_quad, vol
from stiff import principled_ball

SEEDS = (0, 1, 2)
ITERATIONS = 20
RATE = 0.03
SPREADS = 4.0  # standard errors of the difference of the two means
ATOL = 2e-3

_rng = np.random.default_rng(3)
# name -> (files, main, starts, the integrator both use, its depth, spp); every parameter small
# enough (<= 64 components) for the job's records to hold it at each iteration.
CASES = {
    "surface": ({"s.xml": principled_ball(0.2, res=16).encode()}, "s.xml",
                {"ball.bsdf.base_color.value": [0.4] * 3, "ball.bsdf.roughness.value": [0.5]},
                "prb", 4, 8),
    "medium": ({"s.xml": medium_sphere(16, '<bsdf type="null"/>', "0.8, 0.5, 0.3", 1.5,
                                       shape_id="cloud").encode()}, "s.xml",
               {"cloud.interior_medium.albedo.value.value": [0.5] * 3,
                "cloud.interior_medium.sigma_t.value.value": [0.8]}, "prbvolpath", 8, 8),
    "texture": ({"s.xml": textured_quad(16, filename="albedo.exr").encode(),
                 "albedo.exr": exr(_rng.uniform(0.2, 0.9, (4, 4, 3)).astype(np.float32))},
                "s.xml", {"quad.bsdf.reflectance.data": [0.5] * 48}, "prb", 3, 4),
    "grid": ({"s.xml": grid_volume(16).encode(),
              "albedo.vol": vol(_rng.uniform(0.3, 0.95, (2, 2, 2, 3)).astype(np.float32))},
             "s.xml", {"box.interior_medium.albedo.data": [0.6] * 24}, "prbvolpath", 6, 4),
}


def _daemon_runs(stubs, scene: pb.Scene, refs: list[pb.Image], starts, spp: int
                 ) -> tuple[list[np.ndarray], pb.Job]:
    """Per seed, theta_i of every iteration (iterations x components, keys in order)."""
    runs, job = [], None
    for seed in SEEDS:
        spec = pb.JobSpec(scene=scene.name, iterations=ITERATIONS, spp=spp, min_error=0,
                          seed=seed, learning_rate=RATE, schedule=pb.SCHEDULE_CONSTANT,
                          references=[pb.Reference(blob=i.exr_blob, sensor=i.sensor)
                                      for i in refs],
                          parameters=[pb.ParameterSpec(key=k, initial_value=v)
                                      for k, v in starts.items()])
        spec.choices["all"] = "off"
        name = stubs.jobs.CreateJob(pb.CreateJobRequest(spec=spec)).name
        job = wait_state(stubs, name, (pb.JOB_STATE_SUCCEEDED, pb.JOB_STATE_FAILED))
        assert job.state == pb.JOB_STATE_SUCCEEDED, job.error
        history = stubs.jobs.GetJobHistory(pb.GetJobHistoryRequest(name=name)).iterations
        runs.append(np.array([np.concatenate([np.asarray(
            next(v.value for v in r.parameters if v.key == k)) for k in starts])
            for r in history]))
    return runs, job


def _plain_runs(stubs, tmp_path, files, main, refs, starts, integrator, depth, spp, ranges
                ) -> list[np.ndarray]:
    """Per seed, theta_i of every iteration of the plain loop on the same files and
    references."""
    for path, data in files.items():
        (tmp_path / path).write_bytes(data)
    images = {}
    for i in refs:
        images[i.sensor] = tmp_path / f"ref{i.sensor}.exr"
        images[i.sensor].write_bytes(b"".join(c.chunk for c in stubs.blobs.DownloadBlob(
            pb.DownloadBlobRequest(name=i.exr_blob))))
    spec = {"variant": "llvm_ad_rgb", "seeds": [s * 1_000_003 for s in SEEDS],
            "xml": str(tmp_path / main), "reference": str(images.pop(0)),
            "more_references": {str(k): str(v) for k, v in images.items()},
            "start": starts, "iterations": ITERATIONS, "spp": spp, "integrator": integrator,
            "max_depth": depth, "ranges": ranges, "rate": RATE}
    (tmp_path / "spec.json").write_text(json.dumps(spec))
    out = subprocess.run([sys.executable, str(ROOT / "bench" / "plain.py"), "--loop",
                          str(tmp_path / "spec.json")], capture_output=True, text=True,
                         timeout=600, check=True)
    return [np.array([np.concatenate([np.asarray(it[k]) for k in starts])
                      for it in json.loads(line)["values"]])
            for line in out.stdout.splitlines()]


@pytest.mark.parametrize("case", list(CASES))
def test_the_plain_preset_follows_mitsubas_adam_loop(stubs, tmp_path, case):
    files, main, starts, integrator, depth, spp = CASES[case]
    scene = create_scene(stubs, files, main)
    refs = list(stubs.scenes.RenderScene(pb.RenderSceneRequest(name=scene.name, spp=256,
                                                               seed=5)).images)
    listed = {p.key: p for p in stubs.scenes.ListSceneParameters(
        pb.ListSceneParametersRequest(name=scene.name)).parameters}
    ranges = {k: (listed[k].min, listed[k].max) for k in starts}
    daemon, job = _daemon_runs(stubs, scene, refs, starts, spp)
    assert job.integrator == integrator and all(not c.on for c in job.choices)
    plain = _plain_runs(stubs, tmp_path, files, main, refs, starts, integrator, depth, spp, ranges)
    d, p = np.array(daemon), np.array(plain)  # seeds x iterations x components
    assert d.shape == p.shape
    moved = np.abs(p[:, -1] - p[:, 0]).mean()
    assert moved > 10 * ATOL, "the parameters hardly moved: nothing to compare"
    se = np.sqrt((d.var(axis=0, ddof=1) + p.var(axis=0, ddof=1)) / len(SEEDS))
    gap = np.abs(d.mean(axis=0) - p.mean(axis=0))
    worst = np.unravel_index(np.argmax(gap - SPREADS * se), gap.shape)
    assert np.all(gap <= SPREADS * se + ATOL), (
        f"{case}: at iteration {worst[0]}, component {worst[1]}: daemon "
        f"{d.mean(axis=0)[worst]:.5f}, plain {p.mean(axis=0)[worst]:.5f}, seeds' standard "
        f"error {se[worst]:.2g}")

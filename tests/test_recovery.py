"""Recovery: parameters come back to the truth they were rendered from.

Each case renders a reference from known values (the scene's own), starts from a perturbed
guess, and checks the result against the truth within a stated tolerance.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from matopt_api.v1 import matopt_pb2 as pb

from conftest import wait_state
from scenes import PRINCIPLED, create_scene

# The Cornell box's true wall colours (mitsuba.cornell_box()).
WALLS = {
    "red.reflectance.value": [0.570068, 0.0430135, 0.0443706],
    "green.reflectance.value": [0.105421, 0.37798, 0.076425],
    "white.reflectance.value": [0.885809, 0.698859, 0.666422],
}


def test_demo_recovers_the_wall_colours_at_64px(daemon, tmp_path):
    """`matopt demo` against a running daemon: grey walls back to their colours within 0.03."""
    out = tmp_path / "demo"
    run = subprocess.run([sys.executable, "-m", "matopt_client.cli", "--server", daemon.address, "demo",
                          "--resolution", "64", "--out", str(out)],
                         capture_output=True, text=True, timeout=600,
                         env=dict(os.environ, MATOPT_TOKEN=""))
    assert run.returncode == 0, run.stderr
    exported = json.loads((out / "parameters.json").read_text())
    for key, truth in WALLS.items():
        assert exported["initial"][key] == pytest.approx([0.5] * 3)
        assert exported["parameters"][key] == pytest.approx(truth, abs=0.03), key
    assert "max abs error" in run.stdout


# Thesis Table 2's object (base_color 0.41/0.82/0.99, eta 1.49, mostly transmissive) with a
# roughness prb can identify: below ~0.03 the principled BSDF's alpha floor hides it.
PRINCIPLED_TRUTH = {
    "shape_2.bsdf.base_color.value": ([0.41, 0.82, 0.99], [0.5, 0.5, 0.5], 0.03),
    "shape_2.bsdf.roughness.value": ([0.3], [0.5], 0.03),
    "shape_2.bsdf.spec_trans.value": ([0.7], [0.3], 0.03),
    "shape_2.bsdf.eta": ([1.49], [1.3], 0.03),
}


def test_principled_object_recovers_color_roughness_transmission_and_eta(stubs):
    scene = create_scene(stubs, {"principled.xml": PRINCIPLED.encode()}, "principled.xml")
    truth = {p.key: list(p.value) for p in stubs.scenes.ListSceneParameters(
        pb.ListSceneParametersRequest(name=scene.name)).parameters}
    for key, (value, _, _) in PRINCIPLED_TRUTH.items():
        assert truth[key] == pytest.approx(value, abs=1e-6)
    ref = stubs.scenes.RenderScene(pb.RenderSceneRequest(name=scene.name, spp=512)).images[0]
    job = stubs.jobs.CreateJob(pb.CreateJobRequest(spec=pb.JobSpec(
        # the defaults: 16 spp, cosine decay, learning rate 0.1 (eta 0.01)
        scene=scene.name, iterations=200, min_error=0,
        references=[pb.Reference(blob=ref.exr_blob, filename="ref.exr")],
        parameters=[pb.ParameterSpec(key=k, initial_value=start)
                    for k, (_, start, _) in PRINCIPLED_TRUTH.items()])))
    done = wait_state(stubs, job.name, (pb.JOB_STATE_SUCCEEDED, pb.JOB_STATE_FAILED), timeout=600)
    assert done.state == pb.JOB_STATE_SUCCEEDED, done.error
    assert done.integrator == "prb"
    last = {p.key: list(p.value) for p in stubs.jobs.GetJobResult(
        pb.GetJobResultRequest(name=job.name, which=pb.WHICH_LAST)).parameters}
    for key, (value, _, tolerance) in PRINCIPLED_TRUTH.items():
        assert last[key] == pytest.approx(value, abs=tolerance), key

"""Recovery of every kind of parameter the thesis tool reconstructed, and more.

Each case renders a reference from known values (the scene's own), starts from the thesis's
kind of initial guess, and checks the recovered values against the truth within a stated
tolerance; for textures and grids, an error bound over all texels.
"""

from __future__ import annotations

import io

import numpy as np
import pytest

from matopt_api.v1 import matopt_pb2 as pb

from conftest import wait_state
from scenes import (QUAD_CORNERS, QUAD_IN_FRONT, colored_mesh, create_scene,
                    glass_with_medium, grid_volume, png, quad_obj, textured_quad, upload, vol)


def recover(stubs, files: dict[str, bytes], main: str, starts: dict[str, list[float] | str],
            iterations: int, spp: int = 4, reference_spp: int = 256,
            learning_rates: dict[str, float] | None = None,
            smoothness: dict[str, float] | None = None, **spec):
    """Runs a job from ``starts`` (values, or a blob name of a .npy) and returns
    (parameters as listed, recovered LAST values, finished job)."""
    scene = create_scene(stubs, files, main)
    params = {p.key: p for p in stubs.scenes.ListSceneParameters(
        pb.ListSceneParametersRequest(name=scene.name)).parameters}
    ref = stubs.scenes.RenderScene(pb.RenderSceneRequest(name=scene.name,
                                                         spp=reference_spp)).images
    selection = []
    for key, start in starts.items():
        assert key in params, f"{key} not in {sorted(params)}"
        p = pb.ParameterSpec(key=key)
        if key in (learning_rates or {}):
            p.learning_rate = learning_rates[key]
        p.smoothness = (smoothness or {}).get(key, 0.0)
        if isinstance(start, str):
            p.initial_blob = start
        else:
            p.initial_value[:] = start
        selection.append(p)
    job = stubs.jobs.CreateJob(pb.CreateJobRequest(spec=pb.JobSpec(
        scene=scene.name, iterations=iterations, spp=spp, min_error=0,
        references=[pb.Reference(blob=i.exr_blob, filename=f"ref{i.sensor}.exr") for i in ref],
        parameters=selection, **spec)))
    done = wait_state(stubs, job.name, (pb.JOB_STATE_SUCCEEDED, pb.JOB_STATE_FAILED), timeout=600)
    assert done.state == pb.JOB_STATE_SUCCEEDED, done.error
    last = stubs.jobs.GetJobResult(pb.GetJobResultRequest(name=job.name, which=pb.WHICH_LAST))
    values = {}
    for v in last.parameters:
        if v.blob:
            data = b"".join(c.chunk for c in stubs.blobs.DownloadBlob(
                pb.DownloadBlobRequest(name=v.blob)))
            values[v.key] = np.load(io.BytesIO(data)).ravel()
        else:
            values[v.key] = np.array(v.value)
    return params, values, done


def export(daemon, job: str, directory):
    """What a user gets from `matopt job export --which last`."""
    from matopt_client.client import connect
    from matopt_client.export import export_job
    client = connect(daemon.address)
    try:
        return export_job(client, job, directory, "last")
    finally:
        client.close()


def read_vol(path) -> np.ndarray:
    data = path.read_bytes()
    assert data[:4] == b"VOL\x03"
    x, y, z, c = np.frombuffer(data[8:24], dtype="<i4")
    return np.frombuffer(data[48:], dtype="<f4").reshape(z, y, x, c)


def npy_blob(stubs, array) -> str:
    buf = io.BytesIO()
    np.save(buf, np.asarray(array, dtype=np.float32))
    return f"blobs/{upload(stubs, buf.getvalue())}"


def test_principled_base_color_texture_from_black(stubs):
    """Thesis Table 3: a principled BSDF's base_color bitmap, from an empty (black) bitmap."""
    texels = np.random.default_rng(2).uniform(0.1, 0.9, (4, 4, 3))
    files = {"quad.xml": textured_quad(bsdf="principled", colour="base_color").encode(),
             "textures/albedo.png": png(texels)}
    key = "quad.bsdf.base_color.data"
    params, got, _ = recover(stubs, files, "quad.xml", {key: [0.0] * 48}, iterations=120)
    assert params[key].kind == pb.PARAMETER_KIND_TEXTURE
    rmse = np.sqrt(np.mean((got[key] - np.array(params[key].value)) ** 2))
    assert rmse < 0.04, rmse


def test_thindielectric_with_homogeneous_medium(stubs):
    """Thesis Table 4's other material: a thin dielectric shell around a medium; the medium's
    albedo and sigma_t (prbvolpath). The shell's eta is left at its value: it acts only through
    ideal specular directions, which prb's detached sampling does not differentiate (in our
    trials eta drifted from 1.3 to 1.13, away from 1.49), so it is not identifiable here."""
    starts = {"blob.interior_medium.albedo.value.value": [0.5] * 3,
              "blob.interior_medium.sigma_t.value.value": [0.9]}
    params, got, done = recover(stubs, {"thin.xml": glass_with_medium(thin=True).encode()},
                                "thin.xml", starts, iterations=150, spp=16)
    assert done.integrator == "prbvolpath"
    tolerance = {"blob.interior_medium.albedo.value.value": 0.08,
                 "blob.interior_medium.sigma_t.value.value": 0.1}
    for key, tol in tolerance.items():
        assert got[key] == pytest.approx(list(params[key].value), abs=tol), (key, got[key])


def test_bitmap_texture_from_black(stubs, daemon, tmp_path):
    """An 8-bit PNG texture becomes optimizable without editing the XML (thesis Figure 15:
    'empty (black) bitmap' start). Truth: 4x4 texels of distinct colours."""
    rng = np.random.default_rng(1)
    texels = rng.uniform(0.1, 0.9, (4, 4, 3))
    files = {"quad.xml": textured_quad().encode(), "textures/albedo.png": png(texels)}
    params, got, done = recover(stubs, files, "quad.xml",
                                {"quad.bsdf.reflectance.data": [0.0] * 48}, iterations=120)
    key = "quad.bsdf.reflectance.data"
    assert params[key].kind == pb.PARAMETER_KIND_TEXTURE and list(params[key].shape) == [4, 4, 3]
    truth = np.array(params[key].value)
    rmse = np.sqrt(np.mean((got[key] - truth) ** 2))
    assert rmse < 0.03, (rmse, got[key] - truth)
    # The export holds the texture as an image and the values as the daemon reported them.
    out = export(daemon, done.name, tmp_path)
    import json
    exported = json.loads((out.directory / "parameters.json").read_text())
    assert np.array(exported["parameters"][key]) == pytest.approx(got[key], abs=1e-6)
    assert exported["shapes"][key] == [4, 4, 3]
    assert (out.directory / "quad.bsdf.reflectance.data.png").read_bytes()[:4] == b"\x89PNG"
    assert (out.directory / "quad.bsdf.reflectance.data.exr").exists()
    assert (out.directory / "sensor0_error.png").exists()
    # The optimized scene loads with the recovered texture in place of the PNG.
    _, loaded = load_exported_scene(out.directory, "scene_optimized.xml")
    assert np.allclose(np.array(loaded[key]).ravel(), got[key], atol=1e-4)


def test_roughdielectric_with_homogeneous_medium(stubs, daemon, tmp_path):
    """Thesis Table 4 with prbvolpath: alpha, eta, the medium's albedo and sigma_t, jointly.

    As in the thesis (eta's learning rate 0.003-0.01), the interface parameters get a smaller
    learning rate than the medium: with 0.03 for all four, alpha and eta wander while the
    medium is still far off, and the joint problem drifts away (alpha to 0, eta to 1.17).
    alpha steps in log space: its 0.1 is a 10% change, 0.01 in alpha terms at the truth.

    At 64 px: at 32 px alpha and eta trade off along a valley the image barely constrains, and
    over ten seeds they landed anywhere in 0.08-0.13 and 1.46-1.53; at 64 px, 0.08-0.11 and
    1.475-1.50."""
    truth = {"blob.bsdf.alpha.value": [0.1], "blob.bsdf.eta": [1.49],
             "blob.interior_medium.albedo.value.value": [0.412, 0.824, 0.999],
             "blob.interior_medium.sigma_t.value.value": [0.4]}
    starts = {"blob.bsdf.alpha.value": [0.3], "blob.bsdf.eta": [1.55],
              "blob.interior_medium.albedo.value.value": [0.5, 0.5, 0.5],
              "blob.interior_medium.sigma_t.value.value": [0.9]}
    params, got, done = recover(stubs, {"glass.xml": glass_with_medium(64).encode()}, "glass.xml",
                                starts, iterations=200, spp=16,
                                learning_rates={"blob.bsdf.alpha.value": 0.1,
                                                "blob.bsdf.eta": 0.01})
    assert done.integrator == "prbvolpath" and "media" in done.integrator_reason
    for key, value in truth.items():
        assert list(params[key].value) == pytest.approx(value, abs=1e-6)
    # albedo and sigma_t trade off against each other (a denser, darker medium looks alike),
    # hence the wider bounds for them: over seeds 0-2 sigma_t ended at 0.43-0.52 stepped
    # linearly (linear_extinction), 0.42-0.47 in log space.
    tolerance = {"blob.bsdf.alpha.value": 0.03, "blob.bsdf.eta": 0.03,
                 "blob.interior_medium.albedo.value.value": 0.08,
                 "blob.interior_medium.sigma_t.value.value": 0.15}
    for key, tol in tolerance.items():
        assert got[key] == pytest.approx(truth[key], abs=tol), (key, got[key])
    out = export(daemon, done.name, tmp_path).directory
    _, loaded = load_exported_scene(out, "scene_optimized.xml")
    for key in truth:
        assert np.array(loaded[key]).ravel() == pytest.approx(got[key], abs=1e-5), key


def test_per_vertex_colours_from_black(stubs, daemon, tmp_path):
    """Thesis Table 8: per-vertex colours of a mesh, from black."""
    xml, ply = colored_mesh()
    params, got, done = recover(stubs, {"mesh.xml": xml.encode(), "grid.ply": ply},
                                "mesh.xml", {"grid.vertex_color": [0.0] * 27}, iterations=150)
    assert params["grid.vertex_color"].kind == pb.PARAMETER_KIND_VERTEX_ARRAY
    truth = np.array(params["grid.vertex_color"].value)
    assert np.abs(got["grid.vertex_color"] - truth).max() < 0.05
    out = export(daemon, done.name, tmp_path).directory
    import json
    exported = json.loads((out / "parameters.json").read_text())
    assert np.array(exported["parameters"]["grid.vertex_color"]) == pytest.approx(
        got["grid.vertex_color"], abs=1e-6)
    assert np.array_equal(np.load(out / "grid.vertex_color.npy").ravel(),
                          got["grid.vertex_color"].astype(np.float32))
    _, loaded = load_exported_scene(out, "scene_optimized.xml")
    assert np.allclose(np.array(loaded["grid.vertex_color"]), got["grid.vertex_color"],
                       atol=1e-6)


def test_grid_volume_albedo_from_grey(stubs, daemon, tmp_path):
    """Thesis Table 5: a heterogeneous medium's albedo grid (4x4x4 RGB), started from a grey
    grid given as a .npy blob, since 192 values are too many to travel inline."""
    truth = np.random.default_rng(0).uniform(0.3, 0.95, (4, 4, 4, 3)).astype(np.float32)
    start = npy_blob(stubs, np.full((4, 4, 4, 3), 0.6))
    key = "box.interior_medium.albedo.data"
    params, got, done = recover(stubs, {"vol.xml": grid_volume().encode(),
                                        "albedo.vol": vol(truth)}, "vol.xml",
                                {key: start}, iterations=200, spp=8, reference_spp=1024)
    assert params[key].kind == pb.PARAMETER_KIND_VOLUME_GRID and list(params[key].shape) == [4, 4, 4, 3]
    assert done.integrator == "prbvolpath"
    error = got[key] - truth.ravel()
    # The 8 interior voxels are seen only through the others and converge slowly; the bound is
    # on the RMSE over all 64 voxels and 3 channels. Noise in the reference shifts the optimum
    # the weakly seen voxels settle on: over six seeds the RMSE ended at 0.10-0.13 against a
    # 256-spp reference and at 0.07-0.10 against this one.
    start_rmse = np.sqrt(np.mean((0.6 - truth) ** 2))
    assert start_rmse > 0.18
    assert np.sqrt(np.mean(error ** 2)) < 0.125
    # Exported as .npy and as a Mitsuba .vol, both reloading to the reported values.
    out = export(daemon, done.name, tmp_path).directory
    npy = np.load(out / f"{key}.npy")
    assert npy.shape == (4, 4, 4, 3) and np.allclose(npy.ravel(), got[key])
    assert np.allclose(read_vol(out / f"{key}.vol"), npy)
    _, loaded = load_exported_scene(out, "scene_optimized.xml")
    assert np.allclose(np.array(loaded[key]).ravel(), got[key], atol=1e-6)



def test_emitter_radiance_alone_and_jointly_with_a_wall(stubs):
    """Area light radiance (values near 18, far outside [0, 1]) alone, then together with the
    red wall's reflectance (the scales differ by two orders of magnitude), all at the default
    learning rate: radiance is optimized in log space, so 0.1 is a 10% step at any scale."""
    light, red = "light.emitter.radiance.value", "red.reflectance.value"
    truth = {light: [18.387, 13.9873, 6.75357], red: [0.570068, 0.0430135, 0.0443706]}
    scene = stubs.scenes.CreateScene(pb.CreateSceneRequest(overrides={"resx": "32",
                                                                      "resy": "32"}))
    ref = stubs.scenes.RenderScene(pb.RenderSceneRequest(name=scene.name, spp=256)).images[0]
    for selection in ([light], [light, red]):
        job = stubs.jobs.CreateJob(pb.CreateJobRequest(spec=pb.JobSpec(
            scene=scene.name, iterations=150, min_error=0,
            references=[pb.Reference(blob=ref.exr_blob)],
            parameters=[pb.ParameterSpec(key=light, initial_value=[10, 10, 10])]
            + ([pb.ParameterSpec(key=red, initial_value=[0.3, 0.3, 0.3])]
               if red in selection else []))))
        done = wait_state(stubs, job.name, (pb.JOB_STATE_SUCCEEDED, pb.JOB_STATE_FAILED))
        assert done.state == pb.JOB_STATE_SUCCEEDED, done.error
        last = {v.key: np.array(v.value) for v in stubs.jobs.GetJobResult(
            pb.GetJobResultRequest(name=job.name, which=pb.WHICH_LAST)).parameters}
        relative = np.abs(last[light] - truth[light]) / np.array(truth[light])
        assert relative.max() < 0.05, (selection, last[light])
        if red in selection:
            assert last[red] == pytest.approx(truth[red], abs=0.04)


def load_exported_scene(directory, main: str):
    """The exported optimized scene as Mitsuba sees it (the test may use Mitsuba; a client
    never needs to)."""
    import mitsuba as mi
    mi.set_variant("scalar_rgb")
    path = directory / "scene" / main
    assert path.exists(), sorted(p.name for p in (directory / "scene").rglob("*"))
    scene = mi.load_file(str(path), optimize=False)
    return scene, mi.traverse(scene)


@pytest.mark.slow
def test_vertex_positions_with_a_projective_integrator(stubs, daemon, tmp_path):
    """Geometry: a quad shifted by (0.2, 0.1) slides back onto its silhouette. Needs projective
    sampling of visibility edges (direct_projective here: ~2 s per iteration even at 16x16 on
    2 CPU cores, hence `slow`). Depth along the view axis is barely observable, so the check is
    on the quad's centre in the image plane; the export writes the moved mesh as PLY."""
    truth = np.array(QUAD_CORNERS, dtype=np.float32)
    key = "quad.vertex_positions"
    start = (truth + [0.2, 0.1, 0]).ravel().tolist()
    params, got, done = recover(stubs, {"quad.xml": QUAD_IN_FRONT.encode(),
                                        "quad.obj": quad_obj()}, "quad.xml", {key: start},
                                iterations=30, spp=8, learning_rates={key: 0.02})
    assert done.integrator == "direct_projective", done.integrator_reason
    centre = got[key].reshape(-1, 3).mean(axis=0)
    assert np.abs(centre[:2]).max() < 0.05, centre
    out = export(daemon, done.name, tmp_path).directory
    assert (out / "scene" / "meshes" / "quad.ply").read_bytes().startswith(b"ply")
    _, loaded = load_exported_scene(out, "scene_optimized.xml")
    assert np.allclose(np.array(loaded[key]), got[key], atol=1e-5)


@pytest.mark.parametrize("medium, warned", [("heterogeneous", True), ("homogeneous", False)])
def test_a_constant_sigma_t_in_a_heterogeneous_medium_is_flagged(stubs, medium, warned):
    """prbvolpath's gradient of a heterogeneous medium's constant sigma_t lacks the
    transmittance's share (no null collisions against a majorant equal to it): the job says so,
    and points to a homogeneous medium, which it does not flag."""
    truth = np.random.default_rng(0).uniform(0.3, 0.95, (4, 4, 4, 3)).astype(np.float32)
    xml = grid_volume(16).replace('type="heterogeneous"', f'type="{medium}"')
    key = "box.interior_medium.sigma_t.value.value"
    params, got, done = recover(stubs, {"vol.xml": xml.encode(), "albedo.vol": vol(truth)},
                                "vol.xml", {key: [1.0]}, iterations=2, spp=1, reference_spp=4)
    flagged = [n for n in done.notes
               if n.startswith(f"{key}: a constant sigma_t in a heterogeneous medium")]
    assert bool(flagged) == warned, done.notes
    if warned:
        assert "a homogeneous medium, whose albedo may still be a grid" in flagged[0]

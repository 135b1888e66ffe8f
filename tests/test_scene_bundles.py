"""Scenes as their authors ship them: file names relative to the project's root (the directory
Mitsuba was run from) with Windows separators, files shared between scenes in sibling folders,
includes elsewhere; what is missing reported at once; nothing outside the bundle reached; and
what a large parameter costs said where it is listed and where it is selected.

The CLI runs as a subprocess against a real daemon.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import grpc
import numpy as np
import pytest

from matopt_api import costs

from scenes import camera, create_scene, exr, grid_volume, png, vol

RED = (0.8, 0.1, 0.1)
QUAD_PLY = (b"ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
            b"property float z\nelement face 2\nproperty list uchar int vertex_indices\n"
            b"end_header\n-1 -1 0\n1 -1 0\n1 1 0\n-1 1 0\n3 0 1 2\n3 0 2 3\n")


def shape(mesh: str, texture: str, extra: str = "", id: str = "mesh") -> str:
    return f"""<shape type="ply" id="{id}"><string name="filename" value="{mesh}"/>{extra}
        <bsdf type="diffuse"><texture type="bitmap" name="reflectance">
            <string name="filename" value="{texture}"/></texture></bsdf></shape>"""


def main_xml(mesh: str = r"scenes\shared\meshes\m.ply", texture: str = r"..\textures\red.png",
             include: str = r"scenes\parts\light.xml") -> bytes:
    """The main scene: a root-relative mesh, a texture in a sibling folder named through a
    ``$default``, and an include in another folder."""
    return f"""<scene version="3.0.0">
    <default name="texture" value="{texture}"/>
    <integrator type="path"><integer name="max_depth" value="2"/></integrator>
    {camera(32, fov=20)}
    <include filename="{include}"/>
    {shape(mesh, "$texture")}
</scene>""".encode()


# The included file names the shared mesh and the texture from the root: Mitsuba opens both
# from the main XML's folder, then from the root.
BACK = shape(r"scenes\shared\meshes\m.ply", r"scenes\textures\red.png",
             '<transform name="to_world"><translate z="-2"/></transform>', "back")
LIGHT_XML = f"""<scene version="3.0.0"><emitter type="constant"/>{BACK}</scene>""".encode()


def project(root: Path, **xml) -> Path:
    """The project tree of a Windows-authored scene; returns the main XML."""
    files = {"scenes/a/scene.xml": main_xml(**xml), "scenes/parts/light.xml": LIGHT_XML,
             "scenes/shared/meshes/m.ply": QUAD_PLY,
             "scenes/textures/red.png": png(np.full((4, 4, 3), RED))}
    for path, data in files.items():
        (root / path).parent.mkdir(parents=True, exist_ok=True)
        (root / path).write_bytes(data)
    return root / "scenes/a/scene.xml"


def matopt(daemon, cwd: Path, *args: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, MATOPT_SERVER=daemon.address)
    env.pop("MATOPT_TOKEN", None)
    return subprocess.run([sys.executable, "-m", "matopt_client.cli", *args], capture_output=True,
                          text=True, env=env, cwd=cwd, timeout=600)


def ok(out: subprocess.CompletedProcess) -> str:
    assert out.returncode == 0, out.stderr
    return out.stdout


BUNDLE = {"scenes/a/scene.xml", "scenes/parts/light.xml", "scenes/shared/meshes/m.ply",
          "scenes/textures/red.png"}


@pytest.mark.parametrize("where", ["root", "xml folder", "--root"])
def test_windows_scene_loads_from_anywhere_and_renders_its_texture(daemon, tmp_path, where):
    root = tmp_path / "project"
    xml = project(root)
    if where == "root":
        out = matopt(daemon, root, "scene", "load", r"scenes/a/scene.xml", "--json")
    elif where == "xml folder":
        out = matopt(daemon, xml.parent, "scene", "load", "scene.xml", "--json")
    else:
        out = matopt(daemon, tmp_path, "scene", "load", str(xml), "--root", str(root), "--json")
    scene = json.loads(ok(out))
    assert scene["mainFile"] == "scenes/a/scene.xml"
    assert {f["path"] for f in scene["files"]} == BUNDLE
    ok(matopt(daemon, tmp_path, "scene", "render", scene["name"], "--out", str(tmp_path / "r"),
              "--spp", "4"))
    import mitsuba as mi
    mi.set_variant("scalar_rgb")
    pixels = np.array(mi.Bitmap(str(tmp_path / "r" / "sensor0_render.exr")))[..., :3]
    centre = pixels[12:20, 12:20].reshape(-1, 3).mean(axis=0)
    # The texture's colour (8-bit sRGB, read as linear), lit by the white environment.
    linear = [((c + 0.055) / 1.055) ** 2.4 for c in RED]
    assert centre == pytest.approx(linear, rel=0.15)


def test_every_missing_file_is_named_at_once_with_where_it_was_looked_for(daemon, tmp_path):
    root = tmp_path / "project"
    project(root, mesh=r"scenes\shared\meshes\gone.ply", texture=r"..\textures\gone.png",
            include=r"scenes\parts\gone.xml")
    out = matopt(daemon, root, "scene", "load", "scenes/a/scene.xml")
    assert out.returncode == 2  # a local file missing: the user's to fix
    assert out.stderr.count("matopt: error") == 1, out.stderr
    assert "3 files the scene names cannot be found" in out.stderr
    for written, places in [
            (r"scenes\shared\meshes\gone.ply", ["scenes/a/scenes/shared/meshes/gone.ply",
                                                "scenes/shared/meshes/gone.ply"]),
            (r"..\textures\gone.png", ["scenes/textures/gone.png"]),  # through $texture
            (r"scenes\parts\gone.xml", ["scenes/a/scenes/parts/gone.xml",
                                        "scenes/parts/gone.xml"])]:
        line = next(ln for ln in out.stderr.splitlines() if f"'{written}'" in ln)
        for place in places:
            assert str(root / place) in line, line
    assert "--root DIR" in out.stderr


@pytest.mark.parametrize("written,message", [
    (r"..\..\..\etc\passwd", r"'..\..\..\etc\passwd' (in 'scenes/a/scene.xml') leaves the "
                             "scene bundle"),
    ("/etc/passwd", "absolute path '/etc/passwd' (in 'scenes/a/scene.xml')"),
    (r"C:\Windows\win.ini", r"absolute path 'C:\Windows\win.ini' (in 'scenes/a/scene.xml')"),
    # Inside the bundle from the XML's folder ('etc/passwd'), which the bundle lacks.
    (r"..\..\etc\passwd", r"'..\..\etc\passwd', which is not in the bundle (looked for "
                          "'etc/passwd')"),
])
def test_paths_leaving_the_bundle_are_refused_by_the_daemon(stubs, written, message):
    files = {"scenes/a/scene.xml": main_xml(mesh=written, include="light.xml"),
             "scenes/a/light.xml": b'<scene version="3.0.0"/>',
             "scenes/textures/red.png": png(np.full((4, 4, 3), RED))}
    with pytest.raises(grpc.RpcError) as err:
        create_scene(stubs, files, "scenes/a/scene.xml")
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert message in err.value.details()


def test_a_file_found_after_a_lookup_outside_the_bundle_is_refused(stubs):
    """An include at the root names '../x.xml': Mitsuba tries the root's parent before the
    main XML's folder, where the bundle has it, so the bundle is refused."""
    files = {"scenes/a/scene.xml": b'<scene version="3.0.0"><include filename="inc.xml"/>'
                                   b'</scene>',
             "inc.xml": b'<scene version="3.0.0"><include filename="../x.xml"/></scene>',
             "scenes/x.xml": b'<scene version="3.0.0"/>'}
    with pytest.raises(grpc.RpcError) as err:
        create_scene(stubs, files, "scenes/a/scene.xml")
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert "'../x.xml' (in 'inc.xml') leaves the scene bundle" in err.value.details()


def test_the_cli_refuses_a_path_leaving_the_root(daemon, tmp_path):
    root = tmp_path / "project"
    project(root, mesh=r"..\..\..\etc\passwd")
    out = matopt(daemon, tmp_path, "scene", "load", str(root / "scenes/a/scene.xml"),
                 "--root", str(root))
    assert out.returncode == 2  # refused on the client, before an upload
    assert r"'..\..\..\etc\passwd' (in 'scenes/a/scene.xml') leaves the scene bundle" in (
        out.stderr)


# -- large parameters --------------------------------------------------------------------------

def test_set_on_a_default_naming_a_file_loads_that_file(daemon, tmp_path):
    """``--set grid=start.vol`` where ``<default name="grid">`` names the medium's grid: that
    file is uploaded and loaded, the XML's own is not needed."""
    xml = grid_volume(16).replace('value="albedo.vol"', 'value="$grid"').replace(
        '<scene version="3.0.0">', '<scene version="3.0.0"><default name="grid" value="albedo.vol"/>')
    (tmp_path / "scene.xml").write_text(xml)
    (tmp_path / "albedo.vol").write_bytes(vol(np.full((2, 2, 2, 3), 0.5)))
    (tmp_path / "start.vol").write_bytes(vol(np.full((2, 2, 2, 3), 0.8)))
    key = "box.interior_medium.albedo.data"

    def albedo(*load_args: str) -> list[float]:
        scene = ok(matopt(daemon, tmp_path, "scene", "load", "scene.xml", *load_args)).strip()
        listed = json.loads(ok(matopt(daemon, tmp_path, "scene", "params", scene, "--json")))
        return next(p["value"] for p in listed["parameters"] if p["key"] == key)

    assert albedo() == pytest.approx([0.5] * 24)
    assert albedo("--set", "grid=start.vol") == pytest.approx([0.8] * 24)


def test_the_cost_of_a_large_parameter(tmp_path):
    """The 4800x7200 RGB texture of the report: 103,680,000 values, 16 bytes each on the
    device while optimized."""
    line = costs.parameter_cost("wood.reflectance.data", [7200, 4800, 3])
    assert "'wood.reflectance.data' has 103,680,000 values" in line
    assert "1.5 GiB on the renderer's device" in line
    assert "1.2 GiB of worker memory" in line
    assert "207,360 samples" in line
    assert "about 20% to the time" in costs.parameter_cost("k", [7200, 4800, 3], 1_036_800)
    assert not costs.is_large([costs.LARGE_VALUES - 1]) and costs.is_large([costs.LARGE_VALUES])


BIG = r"textures\big.png"


def test_large_texture_cost_is_said_when_listed_and_when_selected(daemon, tmp_path):
    side = int(np.ceil(np.sqrt(costs.LARGE_VALUES / 3)))  # just over the threshold, RGB
    (tmp_path / "textures").mkdir()
    (tmp_path / "textures" / "big.png").write_bytes(png(np.full((side, side, 3), RED)))
    (tmp_path / "scene.xml").write_text(f"""<scene version="3.0.0">
    <integrator type="prb"><integer name="max_depth" value="2"/></integrator>
    {camera(16, fov=20)}
    <emitter type="constant"/>
    <shape type="rectangle" id="quad"><bsdf type="diffuse"><texture type="bitmap"
        name="reflectance"><string name="filename" value="{BIG}"/></texture>
    </bsdf></shape></scene>""")
    scene = ok(matopt(daemon, tmp_path, "scene", "load", "scene.xml")).strip()
    key = "quad.bsdf.reflectance.data"
    listed = matopt(daemon, tmp_path, "scene", "params", scene)
    expected = costs.parameter_cost(key, [side, side, 3])
    assert expected in ok(listed) + listed.stderr
    row = next(ln for ln in listed.stdout.splitlines() if ln.startswith(key))
    assert "large: " in row

    (tmp_path / "ref.exr").write_bytes(exr(np.full((16, 16, 3), 0.5)))
    started = matopt(daemon, tmp_path, "job", "start", scene, "--param", key,
                     "--ref", "ref.exr", "--iterations", "1", "--spp", "1")
    job = ok(started).strip()
    warning = next(ln for ln in started.stderr.splitlines() if ln.startswith("matopt: warning:"))
    assert f"'{key}' has {3 * side * side:,} values" in warning
    assert "to the time of the iteration's renders (256 samples)" in warning
    status = json.loads(ok(matopt(daemon, tmp_path, "job", "status", job, "--json")))
    assert warning.removeprefix("matopt: warning: ") in status["notes"]
    matopt(daemon, tmp_path, "job", "cancel", job)

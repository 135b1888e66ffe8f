"""Procedural test scenes, written by the tests: nothing is downloaded."""

from __future__ import annotations

import hashlib
from pathlib import Path

from matopt.v1 import matopt_pb2 as pb

PRINCIPLED = """<scene version="3.0.0">
    <default name="resx" value="48"/>
    <default name="resy" value="48"/>
    <integrator type="path"><integer name="max_depth" value="6"/></integrator>
    <sensor type="perspective">
        <float name="fov" value="30"/>
        <transform name="to_world"><lookat origin="0, 0.6, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
        <film type="hdrfilm"><integer name="width" value="$resx"/><integer name="height" value="$resy"/>
            <rfilter type="box"/></film>
        <sampler type="independent"><integer name="sample_count" value="16"/></sampler>
    </sensor>
    <emitter type="constant"><rgb name="radiance" value="0.6"/></emitter>
    <shape type="rectangle">
        <transform name="to_world"><scale value="0.8"/><rotate x="1" angle="70"/><translate value="0.8, 2.5, 1.5"/></transform>
        <emitter type="area"><rgb name="radiance" value="8"/></emitter>
    </shape>
    <shape type="rectangle">
        <transform name="to_world"><scale value="3"/><translate value="0, 0, -1.5"/></transform>
        <bsdf type="diffuse">
            <texture type="checkerboard" name="reflectance">
                <rgb name="color0" value="0.1"/><rgb name="color1" value="0.8"/>
                <transform name="to_uv"><scale value="6"/></transform>
            </texture>
        </bsdf>
    </shape>
    <shape type="sphere">
        <bsdf type="principled">
            <rgb name="base_color" value="0.41, 0.82, 0.99"/>
            <float name="roughness" value="0.3"/>
            <float name="spec_trans" value="0.7"/>
            <float name="eta" value="1.49"/>
        </bsdf>
    </shape>
</scene>
"""

# A triangle mesh in a sub-folder, referenced with a Windows separator.
MESH_SCENE = """<scene version="3.0.0">
    <default name="res" value="32"/>
    <sensor type="perspective">
        <transform name="to_world"><lookat origin="0, 0, 3" target="0, 0, 0" up="0, 1, 0"/></transform>
        <film type="hdrfilm"><integer name="width" value="$res"/><integer name="height" value="$res"/></film>
    </sensor>
    <emitter type="constant"/>
    <shape type="obj">
        <string name="filename" value="meshes\\quad.obj"/>
        <bsdf type="diffuse"><rgb name="reflectance" value="0.2, 0.4, 0.6"/></bsdf>
    </shape>
</scene>
"""

QUAD_OBJ = """v -1 -1 0
v 1 -1 0
v 1 1 0
v -1 1 0
f 1 2 3
f 1 3 4
"""


def write_mesh_scene(root: Path) -> Path:
    (root / "meshes").mkdir(parents=True, exist_ok=True)
    (root / "meshes" / "quad.obj").write_text(QUAD_OBJ)
    main = root / "scene.xml"
    main.write_text(MESH_SCENE)
    return main


def upload(stubs, data: bytes) -> str:
    """Uploads bytes as one blob (header + 1 MiB chunks); returns its sha256."""
    sha = hashlib.sha256(data).hexdigest()

    def parts():
        yield pb.UploadBlobRequest(header=pb.UploadBlobRequest.Header(sha256=sha,
                                                                      size_bytes=len(data)))
        for i in range(0, len(data), 1 << 20):
            yield pb.UploadBlobRequest(chunk=data[i:i + (1 << 20)])

    stubs.blobs.UploadBlob(parts())
    return sha


def create_scene(stubs, files: dict[str, bytes], main: str, **overrides) -> pb.Scene:
    bundle = [pb.BundleFile(path=path, sha256=upload(stubs, data)) for path, data in files.items()]
    return stubs.scenes.CreateScene(pb.CreateSceneRequest(
        main_file=main, files=bundle, overrides={k: str(v) for k, v in overrides.items()}))

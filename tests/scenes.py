"""Procedural test scenes, written by the tests: nothing is downloaded."""

from __future__ import annotations

import hashlib
from pathlib import Path

from matopt_api.v1 import matopt_pb2 as pb

def studio(environment: float) -> str:
    """Light and backdrop of the translucent-object scenes: an environment, an area light
    above, and a checkerboard behind the object so that transmission shows."""
    return f"""<emitter type="constant"><rgb name="radiance" value="{environment}"/></emitter>
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
    </shape>"""


PRINCIPLED = f"""<scene version="3.0.0">
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
    {studio(0.6)}
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


def png(pixels, bits: int = 8) -> bytes:
    """A PNG of an (H, W), (H, W, 3) or (H, W, 4) array in [0, 1] (sRGB-encoded values; grey,
    RGB or RGB + straight alpha), 8 or 16 bits per channel, without Mitsuba."""
    import struct
    import zlib

    import numpy as np

    a = np.asarray(pixels, dtype=np.float64)
    a = a[..., None] if a.ndim == 2 else a
    top, kind = (255, ">u1") if bits == 8 else (65535, ">u2")
    values = (np.clip(a, 0, 1) * top + 0.5).astype(kind)
    raw = b"".join(b"\x00" + row.tobytes() for row in values)

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (struct.pack(">I", len(data)) + kind + data
                + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF))

    h, w, c = values.shape
    colour = {1: 0, 3: 2, 4: 6}[c]
    return (b"\x89PNG\r\n\x1a\n"
            + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, bits, colour, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b""))


def exr(pixels) -> bytes:
    """An uncompressed float32 RGB OpenEXR file of an (H, W, 3) linear array, without Mitsuba:
    NaN and Inf stay as they are."""
    import struct

    import numpy as np

    rgb = np.asarray(pixels, dtype="<f4")
    h, w = rgb.shape[:2]

    def attribute(name: str, kind: str, value: bytes) -> bytes:
        return name.encode() + b"\0" + kind.encode() + b"\0" + struct.pack("<i", len(value)) + value

    channels = b"".join(c + b"\0" + struct.pack("<iB3xii", 2, 0, 1, 1) for c in (b"B", b"G", b"R"))
    window = struct.pack("<iiii", 0, 0, w - 1, h - 1)
    header = (b"\x76\x2f\x31\x01" + struct.pack("<I", 2)
              + attribute("channels", "chlist", channels + b"\0")
              + attribute("compression", "compression", b"\0")
              + attribute("dataWindow", "box2i", window)
              + attribute("displayWindow", "box2i", window)
              + attribute("lineOrder", "lineOrder", b"\0")
              + attribute("pixelAspectRatio", "float", struct.pack("<f", 1))
              + attribute("screenWindowCenter", "v2f", struct.pack("<ff", 0, 0))
              + attribute("screenWindowWidth", "float", struct.pack("<f", 1)) + b"\0")
    lines = [struct.pack("<ii", y, 12 * w) + rgb[y, :, ::-1].T.tobytes() for y in range(h)]
    offsets, at = [], len(header) + 8 * h
    for line in lines:
        offsets.append(at)
        at += len(line)
    return header + struct.pack(f"<{h}Q", *offsets) + b"".join(lines)


def vol(grid, lo: float = -0.8, hi: float = 0.8) -> bytes:
    """Mitsuba's binary .vol grid (float32, X fastest) of a (Z, Y, X, C) array; Mitsuba places
    it in the bounding box the header gives ([lo, hi]^3, the cube of grid_volume())."""
    import struct

    import numpy as np

    g = np.asarray(grid, dtype=np.float32)
    z, y, x, c = g.shape
    return (b"VOL" + bytes([3]) + struct.pack("<iiiii", 1, x, y, z, c)
            + struct.pack("<6f", lo, lo, lo, hi, hi, hi) + g.tobytes())


def camera(res: int, origin: str = "0, 0, 4", fov: float = 30, height: int = 0) -> str:
    """A perspective sensor looking at the origin, ``res`` px wide and ``height`` (or ``res``)
    high, with a box filter."""
    return f"""<sensor type="perspective">
        <float name="fov" value="{fov}"/>
        <transform name="to_world"><lookat origin="{origin}" target="0, 0, 0" up="0, 1, 0"/></transform>
        <film type="hdrfilm"><integer name="width" value="{res}"/><integer name="height" value="{height or res}"/>
            <rfilter type="box"/></film>
    </sensor>"""


def textured_quad(res: int = 32, bsdf: str = "diffuse", colour: str = "reflectance",
                  filename: str = "textures/albedo.png", lights: str = "") -> str:
    """A quad filling the view with a colour texture (an 8-bit PNG unless ``filename`` names
    another file), lit by a white environment (and ``lights``, emitters' XML)."""
    return f"""<scene version="3.0.0">
    <integrator type="path"><integer name="max_depth" value="3"/></integrator>
    {camera(res, fov=32)}
    <emitter type="constant"><rgb name="radiance" value="1"/></emitter>
    {lights}
    <shape type="rectangle" id="quad">
        <bsdf type="{bsdf}">
            <texture type="bitmap" name="{colour}">
                <string name="filename" value="{filename}"/>
                <string name="filter_type" value="nearest"/>
            </texture>
        </bsdf>
    </shape>
</scene>
"""


def glass_with_medium(res: int = 32, thin: bool = False) -> str:
    """Thesis Table 4: a rough (or thin) dielectric sphere filled with a homogeneous medium, in
    front of a checkerboard, lit by an environment and an area light."""
    bsdf = ('<bsdf type="thindielectric"><float name="int_ior" value="1.49"/>'
            '<float name="ext_ior" value="1"/></bsdf>') if thin else (
        '<bsdf type="roughdielectric"><float name="alpha" value="0.1"/>'
        '<float name="int_ior" value="1.49"/><float name="ext_ior" value="1"/></bsdf>')
    return medium_sphere(res, bsdf, "0.412, 0.824, 0.999", 0.4)


def medium_sphere(res: int, bsdf: str, albedo: str | float, sigma_t: float,
                  max_depth: int = 8, shape_id: str = "blob") -> str:
    """A sphere with the given interface ``bsdf`` around a homogeneous medium, in the studio
    (checkerboard behind, environment and area light), rendered with volpath."""
    return f"""<scene version="3.0.0">
    <integrator type="volpath"><integer name="max_depth" value="{max_depth}"/></integrator>
    {camera(res, "0, 0.5, 4")}
    {studio(0.5)}
    <shape type="sphere" id="{shape_id}">
        {bsdf}
        <medium type="homogeneous" name="interior">
            <rgb name="albedo" value="{albedo}"/>
            <float name="sigma_t" value="{sigma_t}"/>
        </medium>
    </shape>
</scene>
"""


def colored_mesh(res: int = 32) -> tuple[str, bytes]:
    """A 3x3-vertex grid mesh whose diffuse colour comes from per-vertex colours (a PLY)."""
    verts, faces = [], []
    colors = [(0.8, 0.2, 0.2), (0.2, 0.8, 0.2), (0.2, 0.2, 0.8), (0.8, 0.8, 0.2), (0.5, 0.5, 0.5),
              (0.2, 0.8, 0.8), (0.8, 0.2, 0.8), (0.9, 0.6, 0.3), (0.3, 0.6, 0.9)]
    for j in range(3):
        for i in range(3):
            r, g, b = colors[3 * j + i]
            verts.append(f"{i - 1} {j - 1} 0 {r} {g} {b}")
    for j in range(2):
        for i in range(2):
            a = 3 * j + i
            faces += [f"3 {a} {a + 1} {a + 4}", f"3 {a} {a + 4} {a + 3}"]
    ply = "\n".join(["ply", "format ascii 1.0", f"element vertex {len(verts)}",
                     "property float x", "property float y", "property float z",
                     "property float r", "property float g", "property float b",
                     f"element face {len(faces)}", "property list uchar int vertex_indices",
                     "end_header", *verts, *faces]) + "\n"
    xml = f"""<scene version="3.0.0">
    <integrator type="path"><integer name="max_depth" value="2"/></integrator>
    {camera(res, fov=35)}
    <emitter type="constant"><rgb name="radiance" value="1"/></emitter>
    <shape type="ply" id="grid">
        <string name="filename" value="grid.ply"/>
        <bsdf type="diffuse">
            <texture type="mesh_attribute" name="reflectance">
                <string name="name" value="vertex_color"/>
            </texture>
        </bsdf>
    </shape>
</scene>
"""
    return xml, ply.encode()


def grid_volume(res: int = 32) -> str:
    """A cube of heterogeneous medium whose albedo is a 4x4x4 RGB grid (.vol file), seen by
    two cameras so that every voxel shows."""
    return f"""<scene version="3.0.0">
    <integrator type="volpath"><integer name="max_depth" value="6"/></integrator>
    {camera(res, "2, 1.5, 3.5")}
    {camera(res, "-3.5, -1.5, -2")}
    <emitter type="constant"><rgb name="radiance" value="1"/></emitter>
    <shape type="cube" id="box">
        <transform name="to_world"><scale value="0.8"/></transform>
        <bsdf type="null"/>
        <medium type="heterogeneous" name="interior">
            <volume type="gridvolume" name="albedo">
                <string name="filename" value="albedo.vol"/>
                <string name="filter_type" value="nearest"/>
            </volume>
            <float name="sigma_t" value="1.5"/>
        </medium>
    </shape>
</scene>
"""


QUAD_IN_FRONT = """<scene version="3.0.0">
    <integrator type="direct"/>
    <sensor type="perspective">
        <float name="fov" value="40"/>
        <transform name="to_world"><lookat origin="0, 0, 3" target="0, 0, 0" up="0, 1, 0"/></transform>
        <film type="hdrfilm"><integer name="width" value="16"/><integer name="height" value="16"/>
            <rfilter type="box"/></film>
    </sensor>
    <emitter type="constant"/>
    <shape type="rectangle">
        <transform name="to_world"><scale value="2"/><translate value="0, 0, -1"/></transform>
        <bsdf type="diffuse"><rgb name="reflectance" value="0.1"/></bsdf>
    </shape>
    <shape type="obj" id="quad">
        <string name="filename" value="quad.obj"/>
        <bsdf type="diffuse"><rgb name="reflectance" value="0.8"/></bsdf>
    </shape>
</scene>
"""

QUAD_CORNERS = [[-0.5, -0.5, 0], [0.5, -0.5, 0], [0.5, 0.5, 0], [-0.5, 0.5, 0]]


def quad_obj(corners=QUAD_CORNERS) -> bytes:
    """quad.obj of QUAD_IN_FRONT: two triangles."""
    return ("".join(f"v {x} {y} {z}\n" for x, y, z in corners) + "f 1 2 3\nf 1 3 4\n").encode()


def cornell_with_truth(stubs, size: int, spp: int, keys) -> tuple[pb.Scene, dict, pb.Image]:
    """The built-in Cornell box at size x size, the scene's values of ``keys`` (the truth a
    job should recover) and a reference of sensor 0 rendered from them at ``spp``."""
    scene = stubs.scenes.CreateScene(pb.CreateSceneRequest(
        overrides={"resx": str(size), "resy": str(size)}))
    truth = {p.key: list(p.value) for p in stubs.scenes.ListSceneParameters(
        pb.ListSceneParametersRequest(name=scene.name)).parameters if p.key in keys}
    ref = stubs.scenes.RenderScene(pb.RenderSceneRequest(name=scene.name, spp=spp)).images[0]
    return scene, truth, ref


def icosphere(level: int) -> tuple["np.ndarray", "np.ndarray"]:
    """A unit sphere as an icosahedron subdivided ``level`` times: (vertices, faces), 10 * 4^l
    + 2 vertices (162 at level 2, 642 at 3)."""
    import numpy as np
    t = (1 + 5 ** 0.5) / 2
    verts = [(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0), (0, -1, t), (0, 1, t),
             (0, -1, -t), (0, 1, -t), (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1)]
    faces = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4),
             (11, 10, 2), (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8),
             (3, 8, 9), (4, 9, 5), (2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1)]
    verts = [np.array(v, float) / np.linalg.norm(v) for v in verts]
    for _ in range(level):
        middle: dict[tuple[int, int], int] = {}

        def mid(a: int, b: int) -> int:
            key = (min(a, b), max(a, b))
            if key not in middle:
                m = verts[a] + verts[b]
                verts.append(m / np.linalg.norm(m))
                middle[key] = len(verts) - 1
            return middle[key]

        faces = [f for a, b, c in faces for f in
                 ((a, mid(a, b), mid(c, a)), (b, mid(b, c), mid(a, b)),
                  (c, mid(c, a), mid(b, c)), (mid(a, b), mid(b, c), mid(c, a)))]
    return np.array(verts, np.float32), np.array(faces, np.int64)


def mesh_ply(verts, faces) -> bytes:
    """An ASCII PLY of vertices and (0-based) triangles: Mitsuba keeps a PLY's vertex order
    (an OBJ's follows the faces)."""
    head = (f"ply\nformat ascii 1.0\nelement vertex {len(verts)}\nproperty float x\n"
            f"property float y\nproperty float z\nelement face {len(faces)}\n"
            "property list uchar int vertex_indices\nend_header\n")
    return (head + "".join(f"{x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in verts)
            + "".join(f"3 {a} {b} {c}\n" for a, b, c in faces)).encode()


def views(count: int, distance: float = 4.0) -> list[str]:
    """``count`` camera origins spread over a sphere of ``distance`` (a Fibonacci spiral)."""
    import math
    out = []
    for k in range(count):
        y = 1 - 2 * (k + 0.5) / count
        r, phi = math.sqrt(1 - y * y), k * math.pi * (3 - math.sqrt(5))
        out.append(f"{distance * r * math.cos(phi):.4f}, {distance * y:.4f}, "
                   f"{distance * r * math.sin(phi):.4f}")
    return out


def cameras(res: int, count: int) -> str:
    """``count`` cameras of ``res`` px around the origin (views())."""
    return "".join(camera(res, origin) for origin in views(count))


def box_like(sphere: "np.ndarray") -> "np.ndarray":
    """A unit sphere's vertices pushed toward a cube of half-size 0.7: the shape tests and
    benchmarks pull a sphere of radius 0.7 toward."""
    import numpy as np
    return 0.7 * sphere / np.abs(sphere).max(axis=1, keepdims=True)


def chamfer(a: "np.ndarray", b: "np.ndarray", faces: "np.ndarray") -> float:
    """Symmetric Chamfer distance of two surfaces of the same faces: the mean distance from
    each point sampled on one (vertices, edge midpoints and centroids of its triangles) to the
    nearest sampled on the other, both ways, halved."""
    import numpy as np

    def samples(v: np.ndarray) -> np.ndarray:
        tri = v[faces]
        return np.concatenate([v, tri.mean(axis=1), (tri + np.roll(tri, 1, axis=1)).reshape(
            -1, 3) / 2])

    def nearest(p: np.ndarray, q: np.ndarray) -> float:
        """Mean over p of the distance to q's nearest point, in blocks (bounded memory)."""
        return float(np.concatenate([np.linalg.norm(p[i:i + 256, None] - q[None], axis=-1)
                                     .min(axis=1) for i in range(0, len(p), 256)]).mean())

    p, q = samples(a), samples(b)
    return (nearest(p, q) + nearest(q, p)) / 2


def mesh_in_views(res: int, count: int) -> str:
    """A diffuse mesh (blob.ply, id ``blob``) seen by ``count`` cameras against a hidden
    environment, with a directional light for shading, rendered by direct_projective with
    sppi 0 as Mitsuba's own shape example sets it."""
    return f"""<scene version="3.0.0">
    <integrator type="direct_projective"><integer name="sppi" value="0"/>
        <boolean name="hide_emitters" value="true"/></integrator>
    {cameras(res, count)}
    <emitter type="constant"><rgb name="radiance" value="0.5"/></emitter>
    <emitter type="directional"><vector name="direction" value="-1, -2, -1.5"/>
        <rgb name="irradiance" value="2"/></emitter>
    <shape type="ply" id="blob">
        <string name="filename" value="blob.ply"/>
        <bsdf type="diffuse"><rgb name="reflectance" value="0.7"/></bsdf>
    </shape>
</scene>
"""

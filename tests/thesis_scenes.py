"""Procedural analogues of the thesis's synthetic cases (section 5.1, Tables 2-5), shared by the
tests and bench/thesis_tables.py: nothing is downloaded.

The thesis used the Stanford bunny in an HDR environment. Here the object is a displaced
sphere ("blob", a few thousand triangles, written as PLY with normals and UVs) and the
environment a procedural lat-long EXR (a sky gradient, a sun and dark vertical stripes round
the horizon: sharp features whose reflection and refraction show roughness and eta), both
written by the code. Materials, truths and starts are the thesis's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from scenes import exr, png, vol

OBJECT = "blob"
BOUND = 1.05  # the blob lies inside [-BOUND, BOUND]^3 (the grid of the Table 5 kind fills it)


def blob_mesh(rings: int = 24, segments: int = 48) -> bytes:
    """A displaced UV sphere as binary PLY with vertex normals and UVs (a seam column of
    duplicated vertices keeps the UVs continuous). Radius 1 +- 0.12: lobes at several
    frequencies, so silhouettes and highlights vary over the surface as on a bunny."""
    theta = np.linspace(0, math.pi, rings + 1)[:, None]
    phi = np.linspace(0, 2 * math.pi, segments + 1)[None, :]

    def point(t, p):
        r = (1 + 0.07 * np.sin(3 * t) * np.cos(2 * p) + 0.04 * np.cos(5 * p) * np.sin(t) ** 2
             + 0.03 * np.sin(4 * t + p))
        return np.stack([r * np.sin(t) * np.cos(p), r * np.cos(t), r * np.sin(t) * np.sin(p)], -1)

    pos = point(theta, phi)
    # Normals from the parametric derivatives (central differences), poles pointing out.
    h = 1e-4
    dt = point(theta + h, phi) - point(theta - h, phi)
    dp = point(theta, phi + h) - point(theta, phi - h)
    n = np.cross(dp, dt)
    length = np.linalg.norm(n, axis=-1, keepdims=True)
    n = np.where(length > 1e-9, n / np.maximum(length, 1e-12), pos / np.linalg.norm(pos, axis=-1,
                                                                                   keepdims=True))
    flip = np.sum(n * pos, axis=-1, keepdims=True) < 0
    n = np.where(flip, -n, n)
    uv = np.stack(np.broadcast_arrays(phi / (2 * math.pi), 1 - theta / math.pi), -1)
    verts = np.concatenate([pos, n, uv], -1).reshape(-1, 8)
    idx = lambda i, j: i * (segments + 1) + j  # noqa: E731
    faces = []
    for i in range(rings):
        for j in range(segments):
            a, b, c, d = idx(i, j), idx(i, j + 1), idx(i + 1, j + 1), idx(i + 1, j)
            # Counter-clockwise seen from outside: Mitsuba puts a shape's interior medium
            # (and a dielectric's inside) behind the face normal.
            if i > 0:
                faces.append((a, b, c))
            if i < rings - 1:
                faces.append((a, c, d))
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(verts)}",
              *(f"property float {p}" for p in ("x", "y", "z", "nx", "ny", "nz", "u", "v")),
              f"element face {len(faces)}", "property list uchar int vertex_indices",
              "end_header"]
    face_rows = np.zeros(len(faces), dtype=[("n", "u1"), ("i", "<i4", 3)])
    face_rows["n"], face_rows["i"] = 3, faces
    return ("\n".join(header) + "\n").encode() + verts.astype("<f4").tobytes() + face_rows.tobytes()


def environment(width: int = 128, height: int = 64) -> np.ndarray:
    """A lat-long HDR environment (linear RGB): blue sky over a dark brown ground, a broad
    sun of radiance ~4 (brighter and smaller, its refractions are fireflies whose variance
    swamps the loss at 16 spp), and dark stripes round the horizon."""
    v = (np.arange(height) + 0.5)[:, None] / height       # 0 at the zenith
    u = (np.arange(width) + 0.5)[None, :] / width
    sky = np.stack([0.4 + 0.4 * v, 0.6 + 0.3 * v, 1.0 + 0 * v], -1) * np.ones((1, width, 1))
    ground = np.array([0.25, 0.18, 0.12]) * np.ones((height, width, 3))
    img = np.where((v < 0.5)[..., None], sky, ground)
    stripes = (np.floor(u * 16) % 2 == 0) & (np.abs(v - 0.5) < 0.12)
    img = np.where(stripes[..., None], img * 0.08, img)
    sun = np.exp(-(((u - 0.3) / 0.06) ** 2 + ((v - 0.28) / 0.1) ** 2))
    img = img + 4 * sun[..., None] * np.array([1.0, 0.95, 0.85])
    return img.astype(np.float32)


def base_color_texture(size: int = 16, seed: int = 3) -> np.ndarray:
    """The Table 3 kind's base colour: smooth blobs of colour (texels in [0.15, 0.95])."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:size, 0:size] / size
    out = np.zeros((size, size, 3))
    for c in range(3):
        for _ in range(3):
            fx, fy, ph = rng.uniform(1, 3), rng.uniform(1, 3), rng.uniform(0, 2 * math.pi)
            out[..., c] += np.sin(2 * math.pi * (fx * x + fy * y) + ph)
    return (0.55 + 0.4 * np.tanh(out / 2)).astype(np.float32)


def bump_texture(size: int = 32) -> np.ndarray:
    """Height field of the bump map: ridges in u and v."""
    y, x = np.mgrid[0:size, 0:size] / size
    h = 0.5 + 0.25 * np.sin(2 * math.pi * 6 * x) * np.sin(2 * math.pi * 4 * y)
    return np.repeat(h[..., None], 3, -1).astype(np.float32)


def albedo_grid(size: int = 16, seed: int = 5) -> np.ndarray:
    """The Table 5 kind's albedo grid (Z, Y, X, 3): a smooth colour pattern in [0.2, 0.98]
    varying across the object, around the Table 4 albedo's mean."""
    rng = np.random.default_rng(seed)
    z, y, x = np.mgrid[0:size, 0:size, 0:size] / (size - 1)
    out = np.zeros((size, size, size, 3))
    for c in range(3):
        k = rng.uniform(0.6, 1.4, 3)
        out[..., c] = np.sin(math.pi * (k[0] * x + k[1] * y + k[2] * z) + rng.uniform(0, 6))
    mean = np.array([0.41, 0.82, 0.99]) * 0.85
    return np.clip(mean + 0.3 * out, 0.2, 0.98).astype(np.float32)


def _sensors(res: int, views: int) -> str:
    origins = ["0, 0.8, 4.2", "3.6, 0.4, -2.2", "-3.6, 1.5, -1.6"][:views]
    return "\n".join(f"""<sensor type="perspective">
        <float name="fov" value="36"/>
        <transform name="to_world"><lookat origin="{o}" target="0, 0, 0" up="0, 1, 0"/></transform>
        <film type="hdrfilm"><integer name="width" value="{res}"/><integer name="height" value="{res}"/>
            <rfilter type="box"/></film>
    </sensor>""" for o in origins)


def _scene(res: int, views: int, integrator: str, depth: int, shape_body: str) -> str:
    return f"""<scene version="3.0.0">
    <integrator type="{integrator}"><integer name="max_depth" value="{depth}"/></integrator>
    {_sensors(res, views)}
    <emitter type="envmap"><string name="filename" value="sky.exr"/></emitter>
    <shape type="ply" id="{OBJECT}">
        <string name="filename" value="blob.ply"/>
        {shape_body}
    </shape>
</scene>
"""


@dataclass
class Case:
    """A thesis-table analogue: files to upload, the truth, the start and the targets."""

    name: str
    files: dict[str, bytes]
    start: dict[str, list[float] | np.ndarray]
    truth: dict[str, np.ndarray]
    tolerance: dict[str, float]                 # relative error each target key must reach
    rates: dict[str, float] = field(default_factory=dict)
    integrator: str = "prb"                     # what the plain loop uses
    max_depth: int = 6
    note: str = ""

    @property
    def main(self) -> str:
        return "scene.xml"


def _files(xml: str, **extra: bytes) -> dict[str, bytes]:
    return {"scene.xml": xml.encode(), "blob.ply": blob_mesh(), "sky.exr": exr(environment()),
            **extra}


BSDF = f"{OBJECT}.bsdf"
MEDIUM = f"{OBJECT}.interior_medium"


def table2(res: int = 48, views: int = 1) -> Case:
    """Principled blob: roughness 0.01 (alpha at the floor), base_color, spec_trans 0.9,
    eta 1.49; from the thesis's 0.5 / 0.1 / 0.02 / 1.54."""
    xml = _scene(res, views, "path", 6, """<bsdf type="principled">
            <rgb name="base_color" value="0.41, 0.82, 0.99"/>
            <float name="roughness" value="0.01"/>
            <float name="spec_trans" value="0.9"/>
            <float name="eta" value="1.49"/>
        </bsdf>""")
    k = {"r": f"{BSDF}.roughness.value", "c": f"{BSDF}.base_color.value",
         "t": f"{BSDF}.spec_trans.value", "e": f"{BSDF}.eta"}
    return Case("table2", _files(xml),
                start={k["r"]: [0.5], k["c"]: [0.1] * 3, k["t"]: [0.02], k["e"]: [1.54]},
                truth={k["r"]: np.array([0.01]), k["c"]: np.array([0.41, 0.82, 0.99]),
                       k["t"]: np.array([0.9]), k["e"]: np.array([1.49])},
                tolerance={k["r"]: 0.02, k["c"]: 0.02, k["t"]: 0.02, k["e"]: 0.02})


def table3(res: int = 48, views: int = 1) -> Case:
    """Bump map over a principled BSDF whose base_color is a bitmap: texture from black,
    spec_trans 1.0 from 0.1, eta 1.49 from 1.64 (roughness 0.001, at the floor, left fixed)."""
    xml = _scene(res, views, "path", 6, """<bsdf type="bumpmap">
            <texture type="bitmap" name="bump">
                <string name="filename" value="bump.exr"/>
            </texture>
            <float name="scale" value="0.3"/>
            <bsdf type="principled">
                <texture type="bitmap" name="base_color">
                    <string name="filename" value="color.exr"/>
                    <string name="filter_type" value="bilinear"/>
                </texture>
                <float name="roughness" value="0.001"/>
                <float name="spec_trans" value="1.0"/>
                <float name="eta" value="1.49"/>
            </bsdf>
        </bsdf>""")
    color = base_color_texture()
    inner = f"{BSDF}.nested_bsdf"
    k = {"c": f"{inner}.base_color.data", "t": f"{inner}.spec_trans.value",
         "e": f"{inner}.eta"}
    return Case("table3", _files(xml, **{"color.exr": exr(color), "bump.exr": exr(bump_texture())}),
                start={k["c"]: np.zeros(color.size, np.float32), k["t"]: [0.1], k["e"]: [1.64]},
                truth={k["c"]: color.ravel(), k["t"]: np.array([1.0]), k["e"]: np.array([1.49])},
                tolerance={k["t"]: 0.05, k["e"]: 0.05})


def _medium_body(albedo: str) -> str:
    return f"""<bsdf type="roughdielectric">
            <float name="alpha" value="0.01"/>
            <float name="int_ior" value="1.49"/><float name="ext_ior" value="1"/>
        </bsdf>
        <medium type="homogeneous" name="interior">
            {albedo}
            <float name="sigma_t" value="0.4"/>
        </medium>"""


def table4(res: int = 48, views: int = 1) -> Case:
    """Rough dielectric blob (alpha 0.01) around a homogeneous medium: albedo, sigma_t, eta
    (and alpha) from the thesis's 0.01 / 0.99 / 1.55 / 0.98."""
    xml = _scene(res, views, "volpath", 8,
                 _medium_body('<rgb name="albedo" value="0.41, 0.82, 0.99"/>'))
    k = {"a": f"{BSDF}.alpha.value", "c": f"{MEDIUM}.albedo.value.value",
         "s": f"{MEDIUM}.sigma_t.value.value", "e": f"{BSDF}.eta"}
    return Case("table4", _files(xml),
                start={k["a"]: [0.98], k["c"]: [0.01] * 3, k["s"]: [0.99], k["e"]: [1.55]},
                truth={k["a"]: np.array([0.01]), k["c"]: np.array([0.41, 0.82, 0.99]),
                       k["s"]: np.array([0.4]), k["e"]: np.array([1.49])},
                tolerance={k["c"]: 0.05, k["s"]: 0.05, k["e"]: 0.05},
                integrator="prbvolpath", max_depth=8)


def table5(res: int = 48, views: int = 3, size: int = 16) -> Case:
    """As table4 with the albedo a 16^3 RGB grid filling the blob's bounding box, from grey;
    three views so that every side of the grid shows."""
    grid = albedo_grid(size)
    xml = _scene(res, views, "volpath", 8, _medium_body(f"""<volume type="gridvolume" name="albedo">
                <string name="filename" value="albedo.vol"/>
            </volume>"""))
    k = {"c": f"{MEDIUM}.albedo.data", "s": f"{MEDIUM}.sigma_t.value.value",
         "e": f"{BSDF}.eta"}
    return Case("table5", _files(xml, **{"albedo.vol": vol(grid, -BOUND, BOUND)}),
                start={k["c"]: np.full(grid.size, 0.5, np.float32), k["s"]: [0.99],
                       k["e"]: [1.55]},
                truth={k["c"]: grid.ravel(), k["s"]: np.array([0.4]), k["e"]: np.array([1.49])},
                tolerance={k["s"]: 0.05, k["e"]: 0.05},
                integrator="prbvolpath", max_depth=8)


CASES = {"table2": table2, "table3": table3, "table4": table4, "table5": table5}


def alpha_of_roughness(r: np.ndarray) -> np.ndarray:
    """What the principled BSDF shows of a roughness: alpha = max(0.001, r^2)."""
    return np.maximum(0.001, np.asarray(r, dtype=np.float64) ** 2)


def relative_error(key: str, value, truth) -> float:
    """rmse / rms(truth); a principled roughness compared as alpha (below the floor counts
    as at the floor)."""
    v, t = np.asarray(value, np.float64).ravel(), np.asarray(truth, np.float64).ravel()
    if key.endswith("roughness.value"):
        v, t = alpha_of_roughness(v), alpha_of_roughness(t)
    return float(np.sqrt(np.mean((v - t) ** 2)) / max(np.sqrt(np.mean(t ** 2)), 1e-12))


def psnr(value, truth, peak: float = 1.0) -> float:
    """PSNR in dB of a texture or grid against the truth (values in [0, peak])."""
    mse = float(np.mean((np.asarray(value, np.float64).ravel()
                         - np.asarray(truth, np.float64).ravel()) ** 2))
    return math.inf if mse == 0 else 10 * math.log10(peak * peak / mse)


def correlation(value, truth) -> float:
    """Pearson correlation per texel/voxel of the pattern (each channel's mean removed):
    whether the spatial pattern came back, apart from its average tint."""
    v = np.asarray(value, np.float64).reshape(-1, 3)
    t = np.asarray(truth, np.float64).reshape(-1, 3)
    v, t = v - v.mean(0), t - t.mean(0)
    d = math.sqrt(float(np.sum(v * v)) * float(np.sum(t * t)))
    return float(np.sum(v * t)) / d if d > 0 else 0.0

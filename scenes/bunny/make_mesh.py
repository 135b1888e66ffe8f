"""Writes meshes/bunny.ply: a bunny-like blob (body, head, ears, tail) as a closed mesh.

Made here rather than taken from a scan so that the example ships with nothing of anyone
else's. Each vertex of a UV sphere is pushed out along its direction to a smooth union of
ellipsoids, seen from the body's centre: r = (sum of r_i^8)^(1/8), r_i the far side of
ellipsoid i along that direction (0 where the direction misses it). Run from anywhere:

    python scenes/bunny/make_mesh.py
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

# centre, radii: body, head, two ears, tail (y up, the bunny looking along +x)
ELLIPSOIDS = [((0.0, 0.0, 0.0), (0.55, 0.42, 0.45)),
              ((0.5, 0.3, 0.0), (0.3, 0.27, 0.25)),
              ((0.45, 0.78, 0.12), (0.09, 0.3, 0.1)),
              ((0.45, 0.78, -0.12), (0.09, 0.3, 0.1)),
              ((-0.58, 0.08, 0.0), (0.13, 0.13, 0.13))]
SEGMENTS, RINGS = 96, 48


def radius(d: np.ndarray) -> np.ndarray:
    """Distance from the centre to the surface along unit directions ``d`` (n, 3)."""
    far = []
    for centre, radii in ELLIPSOIDS:
        c, r = np.array(centre), np.array(radii)
        a = ((d / r) ** 2).sum(1)
        b = -2 * (d * c / r ** 2).sum(1)
        k = ((c / r) ** 2).sum() - 1
        disc = b * b - 4 * a * k
        far.append(np.where(disc >= 0, (-b + np.sqrt(np.maximum(disc, 0))) / (2 * a), 0))
    return (np.maximum(np.array(far), 0) ** 8).sum(0) ** (1 / 8)


def mesh() -> tuple[np.ndarray, np.ndarray]:
    theta = np.linspace(0, np.pi, RINGS + 1)[1:-1]
    phi = np.linspace(0, 2 * np.pi, SEGMENTS, endpoint=False)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    d = np.stack([np.sin(t) * np.cos(p), np.cos(t), np.sin(t) * np.sin(p)], -1).reshape(-1, 3)
    d = np.vstack([[0, 1, 0], d, [0, -1, 0]])  # the poles first and last
    vertices = d * radius(d)[:, None]
    faces = []
    ring = lambda i, j: 1 + i * SEGMENTS + j % SEGMENTS  # noqa: E731
    for j in range(SEGMENTS):
        faces.append((0, ring(0, j + 1), ring(0, j)))
        faces.append((len(d) - 1, ring(RINGS - 2, j), ring(RINGS - 2, j + 1)))
        for i in range(RINGS - 2):
            a, b, c, e = ring(i, j), ring(i, j + 1), ring(i + 1, j + 1), ring(i + 1, j)
            faces += [(a, b, c), (a, c, e)]
    return vertices.astype(np.float32), np.array(faces, dtype=np.int32)


def ply(vertices: np.ndarray, faces: np.ndarray) -> bytes:
    header = ("ply\nformat binary_little_endian 1.0\n"
              f"element vertex {len(vertices)}\nproperty float x\nproperty float y\n"
              f"property float z\nelement face {len(faces)}\n"
              "property list uchar int vertex_indices\nend_header\n").encode()
    body = b"".join(struct.pack("<B3i", 3, *f) for f in faces.tolist())
    return header + vertices.astype("<f4").tobytes() + body


if __name__ == "__main__":
    out = Path(__file__).parent / "meshes" / "bunny.ply"
    out.write_bytes(ply(*mesh()))
    print(out)

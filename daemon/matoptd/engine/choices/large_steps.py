"""Vertex positions stepped as Nicolet et al. 2021's "large steps" (``mi.ad.LargeSteps``):
Adam's variable is u = (I + lambda L) v, L the mesh's combinatorial Laplacian, and the scene
renders v = (I + lambda L)^-1 u (a Cholesky solve, cholespy). A vertex's gradient is then
spread over its neighbourhood, so a step moves the surface smoothly instead of pulling single
vertices into spikes, and Adam runs in its uniform mode (one second moment per parameter, the
largest), as Mitsuba's shape example does.

On by default for a mesh of more than SMALL / 3 vertices (a quad or a box moves as a whole
under plain Adam). lambda is the job's (JobSettings.large_steps) or chosen from the mesh:
(I + lambda L)^-1 smooths over about sqrt(lambda) edges, and a closed mesh of V vertices spans
about sqrt(V) of them, so lambda = V / LAMBDA_VERTICES keeps the smoothing a fixed share
(1/16) of the surface whatever its tessellation. A rate not given is a share of the mesh's
extent (its bounding box's diagonal), since u is in scene units. A sphere pulled toward a box
(3 views, 24 px, 60 iterations): the best lambda of 1, 3, 10, 30 and 100 was 1 at 162
vertices, 3 at 642 and 10 at 2562, and the best rate about a tenth of the extent
(docs/benchmarks-history.md, "Large steps by default").
"""

from __future__ import annotations

import math

import mitsuba as mi
import numpy as np

from ...engine_api import SMALL, InvalidInput
from .. import parameters
from .base import Choice

SUFFIX = "vertex_positions"
MISSING = ("large_steps needs cholespy (a sparse Cholesky solver), which this worker lacks: "
           "pip install 'matopt-mitsuba[daemon]' (or cholespy==2.2.0)")
LAMBDA_VERTICES = 256  # lambda = V / this: smoothing over 1/16 of the surface's span
EXTENT_RATE = 0.1      # a rate not given: this share of the mesh's bounding-box diagonal


class LargeSteps(Choice):
    name = "large_steps"

    def select(self, ctx, records):
        asked = ctx.settings.large_steps > 0
        return [k for k, r in records.items() if k.endswith(SUFFIX) and (asked or r.size > SMALL)]

    def setup(self, ctx, records, state) -> None:
        self.applies = bool(self.keys)
        if not self.applies:
            return
        asked = ctx.settings.large_steps
        if not self.on:
            self.why = (f"{', '.join(self.keys)} stepped by plain Adam, each vertex on its own "
                        "(large steps would move the surface smoothly)")
            return
        try:
            import cholespy  # noqa: F401 - mi.ad.LargeSteps imports it when built
        except ImportError:
            if asked:
                raise InvalidInput(MISSING) from None
            self.why = f"{', '.join(self.keys)} stepped by plain Adam: {MISSING}"
            self.keys = []
            return
        everything = mi.traverse(ctx.scene)
        self.steps, self.lambdas, self.extents, self.rates = {}, {}, {}, {}
        for key, r in records.items():
            faces = everything[key[: -len(SUFFIX)] + "faces"]
            vertices = r.start.reshape(-1, 3)
            self.lambdas[key] = asked or len(vertices) / LAMBDA_VERTICES
            self.extents[key] = float(np.linalg.norm(np.ptp(vertices, axis=0))) or 1.0
            self.rates[key] = None if r.rate_given else EXTENT_RATE * self.extents[key]
            # unique vertices by the scene's positions: seams and split normals stay closed
            self.steps[key] = mi.ad.LargeSteps(mi.Float(r.scene), faces, self.lambdas[key])
        lambdas = ", ".join(f"{k} {v:.3g}" for k, v in sorted(self.lambdas.items()))
        chosen = "asked for" if asked else f"vertices / {LAMBDA_VERTICES}"
        self.why = (f"lambda {lambdas} ({chosen}): "
                    "stepped as u = (I + lambda L) v, so a step moves the surface smoothly; "
                    "Adam in its uniform mode (Dr.Jit's is per optimizer: every parameter of "
                    "the job)")
        self.adam_uniform = True

    def encode(self, key: str, value: np.ndarray) -> np.ndarray:
        return parameters.flat(self.steps[key].to_differential(mi.Float(value)))

    def variable(self, key: str, latent: np.ndarray):
        return mi.Float(latent)

    def expand(self, key: str, latent):
        return self.steps[key].from_differential(latent)

    def bounds(self, key: str, lo: float, hi: float) -> tuple[float, float]:
        """u is no position: a range given for the vertices does not bound it."""
        return -math.inf, math.inf

    def rate(self, record, rate: float) -> float:
        return self.rates[record.key] or rate

    def notes(self) -> list[str]:
        def rate(k: str) -> str:
            if self.rates[k] is None:
                return "as given, in scene units of u"
            return (f"{self.rates[k]:.3g}, {EXTENT_RATE:g} of the mesh's extent "
                    f"({self.extents[k]:.3g} scene units), since none was given")
        return [f"{k}: large steps with lambda {self.lambdas[k]:.3g}; its rate {rate(k)}"
                for k in sorted(self.keys)]

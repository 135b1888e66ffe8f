"""Vertex positions stepped as Nicolet et al. 2021's "large steps" (``mi.ad.LargeSteps``):
Adam's variable is u = (I + lambda L) v, L the mesh's combinatorial Laplacian, and the scene
renders v = (I + lambda L)^-1 u (a Cholesky solve, cholespy). A vertex's gradient is then
spread over its neighbourhood, so a step moves the surface smoothly instead of pulling single
vertices into spikes, and Adam runs in its uniform mode (one second moment per parameter, the
largest), as Mitsuba's shape example does. lambda is the job's (JobSettings.large_steps): it
should grow with the mesh's tessellation. On a sphere made box-like (tests/test_large_steps)
it ended closer to the target in Chamfer distance than plain Adam in the same iterations.
"""

from __future__ import annotations

import mitsuba as mi
import numpy as np

from ...engine_api import InvalidInput
from .. import parameters
from .base import Choice

SUFFIX = "vertex_positions"
MISSING = ("large_steps needs cholespy (a sparse Cholesky solver), which this worker lacks: "
           "pip install 'matopt-mitsuba[daemon]' (or cholespy==2.2.0)")


class LargeSteps(Choice):
    name = "large_steps"
    switchable = False  # JobSettings.large_steps (lambda, 0: off) asks for it

    def select(self, ctx, records):
        return [k for k in records if k.endswith(SUFFIX)] if ctx.settings.large_steps > 0 else []

    def setup(self, ctx, records, state) -> None:
        lam = ctx.settings.large_steps
        self.applies = bool(self.keys)
        self.why = (f"asked for, lambda {lam:g}: {', '.join(self.keys)} stepped as "
                    "u = (I + lambda L) v, so a step moves the surface smoothly; Adam in its "
                    "uniform mode (Dr.Jit's is per optimizer: every parameter of the job)")
        if not self.applies:
            return
        try:
            import cholespy  # noqa: F401 - mi.ad.LargeSteps imports it when built
        except ImportError:
            raise InvalidInput(MISSING) from None
        everything = mi.traverse(ctx.scene)
        self.steps = {}
        for key, r in records.items():
            faces = everything[key[: -len(SUFFIX)] + "faces"]
            # unique vertices by the scene's positions: seams and split normals stay closed
            self.steps[key] = mi.ad.LargeSteps(mi.Float(r.scene), faces, lam)
        self.adam_uniform = True

    def encode(self, key: str, value: np.ndarray) -> np.ndarray:
        return parameters.flat(self.steps[key].to_differential(mi.Float(value)))

    def variable(self, key: str, latent: np.ndarray):
        return mi.Float(latent)

    def expand(self, key: str, latent):
        return self.steps[key].from_differential(latent)

    def bounds(self, key: str, lo: float, hi: float) -> tuple[float, float]:
        """u is no position: a range given for the vertices does not bound it."""
        return -np.inf, np.inf

"""An unbounded or large max_depth cut to what the scene needs, measured at the job's start.

Bounces past some depth d may change the image less than anything the job can see: the least
such d renders the same light transport, and a symbolic loop runs only as long as its longest
lane. At the start (unless the user set ``max_depth`` on the scene, which then stands), with
the job's films and spp and the references' masks as weights:

    A, B    two renders at the scene's own depth, independent samples
    s2      = mean_w (A - B)^2 / 2            one render's noise variance per pixel
    c(d)    = mean_w (A - A_d)^2              A_d: A's very samples, paths cut at depth d

and the depth is the least d of LADDER with c(d) < s2 / N: the cut changes the image by less
than the Monte Carlo noise of the mean of the job's N iterations' renders, which is what the
optimum averages. c falls with d (A_d holds every bounce of A up to d), so a binary search
over the ladder takes a few renders. When no d of the ladder below the scene's depth passes,
the scene's depth stands. The bounces a scene needs depend on its values (a medium's albedo
near 0 ends paths early, near 1 not), so this is measured with the scene's own values and with
the job's start, and the larger depth is taken. Table 2 of the thesis (unbounded, 128x96,
16 spp, 100 iterations) measures 16; Table 4 (64) 32 (docs/benchmarks.md). The test is per
pixel, while a cut darkens every pixel alike and so moves a brightness-like parameter more than
one pixel's noise suggests. Measured, the cuts move a least-squares fit at the truth by 0.14%
(Table 2's base_color; bench/information.py) and 0.17% (Table 4's sigma_t, J taken at its
64; docs/benchmarks-history.md), a fifth to two thirds of the spread the job's renders leave.
"""

from __future__ import annotations

import time
from typing import Callable

import drjit as dr
import mitsuba as mi
import numpy as np

from .. import integrator
from .base import Begun, Choice

MEASURED_ABOVE = 16  # a bounded depth up to this stands as the scene says
LADDER = (2, 3, 4, 6, 8, 12, 16, 24, 32, 48, 64, 96, 128, 192, 256)
SEEDS = (0x5EED_0001, 0x5EED_0002)
Measure = Callable[[int], tuple[int, float, float]]  # least -> (depth, change, noise)


class Depth(Choice):
    name = "depth"

    def select(self, ctx, records):
        """Every parameter: measured with the scene's own values as well as the start."""
        return [k for k, r in records.items() if r.scene is not None]

    def setup(self, ctx, records, state) -> None:
        self.scene_values = {k: r.scene for k, r in records.items()}
        chosen = ctx.chosen
        depth = chosen.max_depth
        shown = "unbounded" if depth < 0 else str(depth)
        user = "max_depth" in ctx.settings.scene.overrides
        self.applies = chosen.has_depth and (depth < 0 or depth > MEASURED_ABOVE)
        if user and self.applies:
            self.applies, self.why = False, ""
            return
        if not self.on:
            self.why = f"the scene's max_depth ({shown}) as it stands"
            return
        self.saved = state if state and "depth" in state else None

    def begin(self, ctx) -> Begun | None:
        chosen = ctx.chosen
        depth = chosen.max_depth
        shown = "unbounded" if depth < 0 else str(depth)
        began = time.perf_counter()
        if self.saved is not None:
            cut, change, noise = int(self.saved["depth"][0]), *map(float, self.saved["figures"])
        else:
            def at_scene(least: int) -> tuple[int, float, float]:
                with ctx.holding(self.scene_values):
                    return measure(ctx, depth, least)
            cut, change, noise = larger_cut(at_scene, lambda least: measure(ctx, depth, least),
                                            depth)
        self.depth, self.figures = cut, (change, noise)
        self.setup_seconds = time.perf_counter() - began
        if cut != depth:
            self.why = (f"max_depth {cut} instead of the scene's {shown}: the bounces past {cut} "
                        f"change the image by {change:.3g} (mean square), less than the noise "
                        f"of the mean of the job's renders ({noise:.3g})")
            return Begun(cut, f"the scene's {shown} cut: the bounces past {cut} change the "
                              f"image by {change:.3g} (mean square), less than the noise of "
                              f"the mean of the job's renders ({noise:.3g})")
        self.why = (f"the scene's max_depth {shown} kept: cut anywhere below, the image "
                    f"changes by more than the noise of the mean of the job's renders "
                    f"({noise:.3g})")
        return None

    def state(self):
        if not (self.on and self.applies):
            return {}
        return {"depth": np.array([self.depth], np.int64),
                "figures": np.array(self.figures, np.float64)}


def larger_cut(at_scene: Measure, at_start: Measure, depth: int) -> tuple[int, float, float]:
    """The cut for the scene's own values, then for the job's start from that cut on (the
    start may need more bounces): the larger, with its figures."""
    cut = at_scene(0)
    if cut[0] == depth:
        return cut
    start = at_start(cut[0])
    return start if start[0] != cut[0] else cut


def measure(ctx, depth: int, least: int = 0) -> tuple[int, float, float]:
    """(the depth to render at, the mean square change its cut makes, the noise level it was
    compared with), the scene as it is now; candidates from ``least`` on."""
    def renders(d: int, seed: int) -> dict[int, np.ndarray]:
        it = integrator.make(ctx.chosen, d)
        with dr.suspend_grad():
            return {s: np.array(mi.render(ctx.scene, ctx.params, sensor=s, spp=ctx.spp,
                                          integrator=it, seed=seed), np.float32)[..., :3]
                    for s in ctx.references}

    weights = {s: r.mask() for s, r in ctx.references.items()}
    return least_depth(renders, weights, ctx.settings.iterations, depth, least)


def least_depth(renders: Callable[[int, int], dict[int, np.ndarray]],
                weights: dict[int, np.ndarray], iterations: int, depth: int,
                least: int = 0) -> tuple[int, float, float]:
    """The test itself, on any renderer: ``renders(d, seed)`` gives each sensor's image at
    depth d, the same samples for the same seed; ``weights`` each sensor's pixel weights.
    bench/information.py measures a job's cut with it."""
    total = sum(float(np.sum(w)) for w in weights.values())

    def mean(images: dict[int, np.ndarray]) -> float:
        return sum(float(np.sum(weights[s] * x)) for s, x in images.items()) / max(total, 1.0)

    a, b = renders(depth, SEEDS[0]), renders(depth, SEEDS[1])
    noise = mean({s: (a[s] - b[s]) ** 2 / 2 for s in a}) / max(1, iterations)
    candidates = [d for d in LADDER if d >= least and (depth < 0 or d < depth)]
    best, change = depth, 0.0
    lo, hi = 0, len(candidates) - 1
    while lo <= hi:  # the least candidate that passes; c(d) falls with d
        mid = (lo + hi) // 2
        cut = renders(candidates[mid], SEEDS[0])
        c = mean({s: (a[s] - cut[s]) ** 2 for s in a})
        if c < noise:
            best, change, hi = candidates[mid], c, mid - 1
        else:
            lo = mid + 1
    return best, change, noise

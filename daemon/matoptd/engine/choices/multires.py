"""Textures and grids optimized coarse to fine (the levels' arithmetic: engine/multires.py).

A texture or grid of at least 8 texels a side is optimized first at a quarter (or less) of its
resolution, each coarse texel standing for a block, then at twice that, reaching the full
resolution at half the iterations. A coarse texel is seen by many pixels, so its gradient
carries far less noise than one texel's: the pattern's low frequencies (and its mean tint,
which scalars such as spec_trans would otherwise absorb) settle before its detail. Adam's
state starts afresh at each level (the shape changes).

The job's value for the choice says how (settings.coarse_to_fine): ``nearest`` (the default:
a coarse texel is a block) or ``linear`` upsampling (no block edges), and how many levels.
By default a texture or grid started from given values (``--init``, a restart) that have
detail within the coarsest blocks is left at full resolution: the coarse level would average
that detail away (a grid's RMSE of 0.235 at its --init became 0.258 at the job's first
iteration); naming ``nearest`` or ``linear`` takes it coarse to fine too, from its block
means. A given start without such detail (a constant) goes coarse to fine as the scene's.
"""

from __future__ import annotations

import mitsuba as mi
import numpy as np

from ...settings import coarse_to_fine
from .. import multires, parameters
from .base import Choice


class Multires(Choice):
    name = "multires"

    def _count(self) -> tuple[str, int]:
        return coarse_to_fine(self.settings.choice_value(self.name)) if self.on else ("nearest", 0)

    def select(self, ctx, records):
        count = self._count()[1]
        return [k for k, r in records.items() if len(multires.levels(r.shape, count)) >= 2]

    def setup(self, ctx, records, state) -> None:
        self.iterations = ctx.settings.iterations
        self.mode, count = self._count()
        self.levels: dict[str, list[tuple[int, ...]]] = {}
        given: list[str] = []  # started from given values, left at full resolution
        for key, r in records.items():
            shapes = multires.levels(r.shape, count)
            if (r.initial_given and ctx.settings.choice_value(self.name) == "on"
                    and _detailed(r.start, shapes)):
                given.append(key)
            else:
                self.levels[key] = shapes
        keys = self.keys = sorted(self.levels)
        saved = state.get("levels") if state else None
        self.level = ({k: int(n) for k, n in zip(keys, saved)} if saved is not None
                      else dict.fromkeys(keys, 0))
        self.maps: dict[str, list | None] = {}
        self.applies = bool(keys or given)
        self.why = "; ".join(
            ([f"optimized coarse to fine ({self._steps()}, {self.mode} upsampling; the full "
              f"resolution from iteration {self.iterations // 2}): a coarse texel's "
              "gradient is the sum of a block's, far less noisy, so the pattern's low "
              "frequencies settle before its detail"] if keys and self.on else
             [f"{', '.join(keys)} optimized at full resolution throughout"] if keys else [])
            + ([f"{', '.join(sorted(given))} started from given values, kept as given at full "
                "resolution (multires=nearest or linear takes them coarse to fine from their "
                "block means)"] if given else []))

    def _steps(self) -> str:
        return "; ".join(f"{k}: " + " -> ".join("x".join(map(str, sh[:-1]))
                                                 for sh in self.levels[k])
                         for k in sorted(self.levels))

    def variable(self, key: str, latent: np.ndarray):
        shapes, level = self.levels[key], self.level[key]
        self._map(key, level)
        return self._tensor(key, multires.downsample(latent, shapes[-1], shapes[level]))

    def _tensor(self, key: str, flat: np.ndarray) -> mi.TensorXf:
        return mi.TensorXf(np.asarray(flat, np.float32).reshape(self.levels[key][self.level[key]]))

    def _map(self, key: str, level: int) -> None:
        shapes = self.levels[key]
        self.level[key] = level
        if level == len(shapes) - 1:
            self.maps[key] = None
            return
        self.maps[key] = [(mi.UInt32(i), None if w is None else mi.Float(w))
                          for i, w in multires.taps(shapes[-1], shapes[level], self.mode)]

    def expand(self, key: str, latent):
        made = self.maps.get(key)
        return latent if made is None else multires.upsample(latent, self.levels[key][-1], made)

    def before_render(self, ctx) -> dict[str, object]:
        """Moves each texture or grid to the next level when the iteration reaches it (the
        coarse values carried over, upsampled as the renders saw them)."""
        changed = {}
        for key, shapes in self.levels.items():
            level = multires.level_at(ctx.iteration, self.iterations, len(shapes))
            old = self.level[key]
            if level > old:
                current = parameters.flat(ctx.variable(key))
                self._map(key, level)
                changed[key] = self._tensor(key, multires.apply(
                    current, multires.taps(shapes[level], shapes[old], self.mode)))
        return changed

    def state(self):
        return {"levels": np.array([self.level[k] for k in sorted(self.levels)], np.int32)}

    def notes(self) -> list[str]:
        return [f"{key}: optimized coarse to fine ("
                + " -> ".join("x".join(map(str, sh[:-1])) for sh in shapes)
                + f", {self.mode} upsampling; the full resolution from iteration "
                f"{self.iterations // 2}): the pattern's low frequencies settle "
                "before its detail" for key, shapes in sorted(self.levels.items())]


def _detailed(start: np.ndarray, shapes: list[tuple[int, ...]]) -> bool:
    """Whether the coarsest level's block means would change the start."""
    means = multires.downsample(start, shapes[-1], shapes[0])
    blocks = means[multires.index_map(shapes[-1], shapes[0])]
    return bool(np.abs(blocks - np.ravel(start)).max() > 1e-6 * (1 + np.abs(start).max()))

"""Textures and grids optimized coarse to fine (the levels' arithmetic: engine/multires.py).

A texture or grid of at least 8 texels a side is optimized first at a quarter (or less) of its
resolution, each coarse texel standing for a block, then at twice that, reaching the full
resolution at half the iterations. A coarse texel is seen by many pixels, so its gradient
carries far less noise than one texel's: the pattern's low frequencies (and its mean tint,
which scalars such as spec_trans would otherwise absorb) settle before its detail. Adam's
state starts afresh at each level (the shape changes).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from .. import multires, parameters
from .base import Choice


class Multires(Choice):
    name = "multires"

    def setup(self, loop, state) -> None:
        self.loop = loop
        self.levels: dict[str, list[tuple[int, ...]]] = {}
        for key in loop.parameters:
            value = loop.params[key]
            shapes = multires.levels(tuple(int(n) for n in value.shape)
                                     if dr.is_tensor_v(value) else ())
            if len(shapes) > 1:
                self.levels[key] = shapes
        keys = sorted(self.levels)
        saved = state.get("levels") if state else None
        self.level = ({k: int(n) for k, n in zip(keys, saved)} if saved is not None
                      else dict.fromkeys(keys, 0))
        self.maps: dict[str, mi.UInt32 | None] = {}
        self.applies = bool(keys)
        steps = "; ".join(f"{k}: " + " -> ".join("x".join(map(str, sh[:-1]))
                                                  for sh in self.levels[k]) for k in keys)
        self.why = (f"optimized coarse to fine ({steps}; the full resolution from iteration "
                    f"{loop.settings.iterations // 2}): a coarse texel's gradient is the sum of "
                    "a block's, far less noisy, so the pattern's low frequencies settle before "
                    "its detail" if self.on else
                    f"{', '.join(keys)} optimized at full resolution throughout")

    def variable(self, key: str, latent: np.ndarray):
        if key not in self.levels:
            return None
        shapes, level = self.levels[key], self.level[key]
        self._map(key, level)
        return self._tensor(key, multires.downsample(latent, shapes[-1], shapes[level]))

    def _tensor(self, key: str, flat: np.ndarray) -> mi.TensorXf:
        return mi.TensorXf(np.asarray(flat, np.float32).reshape(self.levels[key][self.level[key]]))

    def _map(self, key: str, level: int) -> None:
        shapes = self.levels[key]
        self.level[key] = level
        full = level == len(shapes) - 1
        self.maps[key] = None if full else mi.UInt32(multires.index_map(shapes[-1],
                                                                        shapes[level]))

    def expand(self, key: str, latent):
        index = self.maps.get(key)
        return latent if index is None else multires.upsample(latent, self.levels[key][-1],
                                                               index)

    def before_render(self, loop, i: int) -> bool:
        """Moves each texture or grid to the next level when iteration i reaches it (the
        coarse values carried over, block by block)."""
        changed = False
        for key, shapes in self.levels.items():
            level = multires.level_at(i, loop.settings.iterations, len(shapes))
            old = self.level[key]
            if level > old:
                current = parameters.flat(loop.opt[key])
                self._map(key, level)
                loop.opt[key] = self._tensor(
                    key, current[multires.index_map(shapes[level], shapes[old])])
                loop.opt.set_learning_rate({key: loop.rates[key]})
                changed = True
        return changed

    def state(self):
        return {"levels": np.array([self.level[k] for k in sorted(self.levels)], np.int32)}

    def notes(self) -> list[str]:
        return [f"{key}: optimized coarse to fine ("
                + " -> ".join("x".join(map(str, sh[:-1])) for sh in shapes)
                + f"; the full resolution from iteration {self.loop.settings.iterations // 2}): "
                "the pattern's low frequencies settle before its detail"
                for key, shapes in sorted(self.levels.items())]

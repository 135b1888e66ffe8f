"""A job's renders: the ones its loss compares (per iteration, seeded so that a restored job
renders what it would have), and the primal ones off the clock (results, image error, a
choice's measurement)."""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass
from typing import Callable

import drjit as dr
import mitsuba as mi
import numpy as np

from .. import engine_api as api
from . import parameters
from .losses import Loss


@dataclass
class Reference:
    image: mi.TensorXf           # (H, W, 3), linear; masked pixels hold 0
    weight: mi.TensorXf | None   # (H, W, 3) in [0, 1]: the mask (and alpha) weight, 0 where the
                                 # reference was NaN/Inf; None when every pixel counts fully
    name: str = ""               # the user's file name, for notes

    def mask(self) -> np.ndarray:
        """The weight as an array (ones when there is none)."""
        if self.weight is None:
            return np.ones(tuple(int(s) for s in self.image.shape), dtype=np.float32)
        return np.asarray(self.weight)


def seed(base: int, iteration: int, slot: int, slots: int) -> int:
    return (base * 1_000_003 + iteration * slots + slot) % 2**32


def render_images(scene: mi.Scene, params: mi.SceneParameters, integrator, sensor: int,
                  spp: int, seeds: list) -> list:
    """A sensor's renders, one per seed (an int or an opaque ``mi.UInt32``), RGB."""
    images = []
    for s in seeds:
        img = mi.render(scene, params, sensor=sensor, spp=spp, integrator=integrator, seed=s)
        images.append(img[..., :3] if img.shape[2] > 3 else img)
    return images


def image_loss(fn: Callable, clamp: bool, images: list, target, weight):
    """``fn`` of renders against a target, both clamped to [0, 1] where ``clamp``."""
    if clamp:
        images = [dr.clip(img, 0.0, 1.0) for img in images]
        target = dr.clip(target, 0.0, 1.0)
    return fn(images, target, weight)


@dataclass
class Renders:
    """The scene, its traversal (kept to the selected keys), the integrator and references;
    ``on_images``: the choices' map of a sensor's renders; ``restore``: the scene back to the
    loop's theta after a render ``holding`` other values; ``frozen``: what renders detached
    images (a choice's at eta +- h, the result images) where the iterations are frozen."""

    scene: mi.Scene
    params: mi.SceneParameters
    references: dict[int, Reference]
    settings: api.JobSettings
    loss: Loss
    on_images: Callable[[int, list], list]
    restore: Callable[[], None]
    integrator: mi.Integrator | None = None
    frozen: Callable | None = None  # render_images as a frozen function (frozen.py), if any

    def seeds(self, i: int, n: int, draw: int = 0) -> list[int]:
        """The render seeds of slot n's sensor at iteration i; ``draw`` picks another set."""
        renders = self.loss.renders
        slots = len(self.references) * renders
        return [(seed(self.settings.seed, i, n * renders + b, slots) + draw) % 2**32
                for b in range(renders)]

    def sensor_images(self, i: int, n: int, sensor: int, draw: int, spp: int) -> list:
        """The renders the loss compares for slot n's sensor at iteration i, as the choices
        make them (times the gain, ...); ``draw`` picks another set of samples."""
        render = self.frozen or render_images
        return self.on_images(sensor, render(self.scene, self.params, self.integrator, sensor,
                                             spp, self.seeds(i, n, draw)))

    def image_loss(self, images: list, ref: Reference):
        """The loss of a sensor's renders against its reference (both clamped to [0, 1] when
        the job asks: an LDR comparison)."""
        return image_loss(self.loss.fn, self.settings.clamp, images, ref.image, ref.weight)

    @contextlib.contextmanager
    def holding(self, values: dict[str, np.ndarray]):
        """The scene with the selected parameters set to ``values``, restored afterwards."""
        for key, v in values.items():
            self.params[key] = parameters.assign(self.params[key], v)
        self.params.update()
        try:
            yield self.scene
        finally:
            self.restore()

    def render(self, values: dict[str, np.ndarray], sensor: int, spp: int,
               gains: dict[int, np.ndarray] | None = None) -> np.ndarray:
        """A primal render with the selected parameters set to ``values``, times the sensor's
        gain when ``gains`` has one (as the loss compares it). Replayed where the iterations
        are frozen, so that the next job on the scene does not trace its result images again."""
        render = self.frozen or render_images
        with self.holding(values), dr.suspend_grad():
            img = render(self.scene, self.params, self.integrator, sensor, spp,
                         [(seed(self.settings.seed, 0, 0, 1) + 7) % 2**32])[0]
        img = np.array(img, dtype=np.float32)
        return img * gains[sensor] if gains and sensor in gains else img

    def image_error(self, values: dict[str, np.ndarray],
                    gains: dict[int, np.ndarray] | None = None) -> float:
        """RMSE of renders (times their gains) at ``image_error_spp`` against the references,
        each pixel by its mask weight, over all sensors."""
        se = n = 0.0
        for sensor, ref in self.references.items():
            img = self.render(values, sensor, self.settings.image_error_spp, gains)
            w = ref.mask()
            se += float(np.sum(w * (img - np.asarray(ref.image)) ** 2))
            n += float(np.sum(w))
        return math.sqrt(se / max(n, 1.0))

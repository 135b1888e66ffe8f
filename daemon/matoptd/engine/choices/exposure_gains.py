"""One RGB gain per reference, fitted with the parameters (JobSettings.fit_exposure).

A photograph was taken at an exposure and white balance of its own: the loss compares
render * g with it, g optimized as log(g) (a step changes it by about 10% at full rate, under
the job's schedule) and clipped to |log g| <= GAIN_LIMIT. Each gain starts at the ratio of
the means of reference and first render, per channel (masked pixels out): from 1, a
photograph several stops off would first drag the reflectances to their bounds while the
gain caught up. Gains are not scene parameters: they travel beside theta.
"""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np

from ..records import GAIN, ParamRecord
from .base import Choice

GAIN_LEARNING_RATE = 0.1  # of log(gain)
GAIN_LIMIT = 10.0         # |log(gain)| bound: a factor of e^10 ~ 22000 either way


class ExposureGains(Choice):
    name = "exposure_gains"
    switchable = False

    def variables(self, ctx) -> list[ParamRecord]:
        """A log gain per reference, u = log g (3 channels), clipped to +-GAIN_LIMIT."""
        if not ctx.settings.fit_exposure:
            return []
        return [ParamRecord(f"gain{sensor}", GAIN, -GAIN_LIMIT, GAIN_LIMIT,
                            GAIN_LEARNING_RATE, np.zeros(3, np.float32), sensor=sensor)
                for sensor in ctx.references]

    def select(self, ctx, records):
        return [k for k, r in records.items() if r.is_gain]

    def setup(self, ctx, records, state) -> None:
        self.applies = ctx.settings.fit_exposure
        self.sensors = {r.sensor: key for key, r in records.items()}  # Adam keys by sensor
        if self.applies:
            self.why = ("asked for (fit_exposure): one RGB gain per reference, fitted in log "
                        "space from the ratio of the means of reference and first render")

    def decode(self, key: str, latent):
        return dr.exp(latent)

    def before_render(self, ctx) -> dict[str, object]:
        """At iteration 0 each gain starts at mean(reference) / mean(render), per channel."""
        if ctx.iteration != 0:
            return {}
        out = {}
        for sensor, key in self.sensors.items():
            ref = ctx.references[sensor]
            w = ref.mask()
            img = ctx.render(ctx.initial, sensor, ctx.spp)
            rendered = np.sum(w * img, axis=(0, 1))
            wanted = np.sum(w * np.asarray(ref.image), axis=(0, 1))
            ratio = np.where(rendered > 0, wanted / np.maximum(rendered, 1e-30), 1.0)
            start = np.log(np.clip(ratio, math.exp(-GAIN_LIMIT), math.exp(GAIN_LIMIT)))
            out[key] = mi.Float(start.astype(np.float32))
        return out

    def on_images(self, ctx, sensor: int, images: list) -> list:
        """render * gain of the sensor's reference (differentiable in the log gain)."""
        if sensor not in self.sensors:
            return images
        key = self.sensors[sensor]
        gain = self.decode(key, ctx.variable(key))
        return [mi.TensorXf(img.array * dr.gather(
            mi.Float, gain, dr.arange(mi.UInt32, dr.width(img.array)) % 3), img.shape)
            for img in images]

    def notes(self) -> list[str]:
        return ["exposure gains: one RGB gain per reference, fitted with the parameters (render "
                "x gain ~ reference), from the ratio of the means of reference and first "
                "render, in log space; a gain trades off against the overall scale of "
                "reflectance and emission, so keep some of it known and fixed (a white "
                "surface, the light's radiance) or the split between them is arbitrary"]

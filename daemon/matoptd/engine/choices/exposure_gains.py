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

from .base import Choice

GAIN_LEARNING_RATE = 0.1  # of log(gain)
GAIN_LIMIT = 10.0         # |log(gain)| bound: a factor of e^10 ~ 22000 either way


class ExposureGains(Choice):
    name = "exposure_gains"
    switchable = False

    def setup(self, loop, state) -> None:
        self.applies = loop.settings.fit_exposure
        if not self.applies:
            return
        self.why = ("asked for (fit_exposure): one RGB gain per reference, fitted in log space "
                    "from the ratio of the means of reference and first render")
        # Adam keys of the log gains, by sensor.
        loop.gains = {sensor: f"gain{sensor}" for sensor in loop.references}
        for key in loop.gains.values():
            loop.opt[key] = mi.Float(0.0, 0.0, 0.0)
            loop.opt.set_learning_rate({key: GAIN_LEARNING_RATE})
            loop.rates[key] = GAIN_LEARNING_RATE

    def before_render(self, loop, i: int) -> bool:
        """At iteration 0 each gain starts at mean(reference) / mean(render), per channel."""
        if i != 0:
            return False
        for sensor, key in loop.gains.items():
            ref = loop.references[sensor]
            w = ref.mask()
            img = loop.render(loop.initial, sensor, loop.spp)
            rendered = np.sum(w * img, axis=(0, 1))
            wanted = np.sum(w * np.asarray(ref.image), axis=(0, 1))
            ratio = np.where(rendered > 0, wanted / np.maximum(rendered, 1e-30), 1.0)
            start = np.log(np.clip(ratio, math.exp(-GAIN_LIMIT), math.exp(GAIN_LIMIT)))
            loop.opt[key] = mi.Float(start.astype(np.float32))
        return False

    def on_images(self, loop, sensor: int, images: list) -> list:
        """render * gain of the sensor's reference (differentiable in the log gain)."""
        if sensor not in loop.gains:
            return images
        gain = dr.exp(loop.opt[loop.gains[sensor]])
        return [mi.TensorXf(img.array * dr.gather(
            mi.Float, gain, dr.arange(mi.UInt32, dr.width(img.array)) % 3), img.shape)
            for img in images]

    def after_step(self, loop, i: int) -> None:
        for key in loop.gains.values():
            loop.opt[key] = dr.clip(loop.opt[key], -GAIN_LIMIT, GAIN_LIMIT)

    def notes(self) -> list[str]:
        return ["exposure gains: one RGB gain per reference, fitted with the parameters (render "
                "x gain ~ reference), from the ratio of the means of reference and first "
                "render, in log space; a gain trades off against the overall scale of "
                "reflectance and emission, so keep some of it known and fixed (a white "
                "surface, the light's radiance) or the split between them is arbitrary"]

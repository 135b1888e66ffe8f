"""A sensor's pixel-channels as the covariance model reads them: both estimates of J, the same
weighed by the loss (K J), the factors of the render noise and the residual per row (a
pixel's channels together: covariance.per_pixel), and their products summed over the sensors
into H, Q and Q_R (covariance.Linearized). The loss says how its rows
are weighed and what noise a step sees (losses.Loss)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from . import covariance
from .losses import LOSSES

if TYPE_CHECKING:
    from .jacobian import Job, Sensor, _Component


@dataclass
class Rows:
    """One sensor's pixel-channels, flattened: two estimates of J (rows x p), the same
    weighted by the loss (K J), and the factors of the render noise and the residual per row
    (covariance.per_pixel)."""

    ja: np.ndarray
    jb: np.ndarray
    ka: np.ndarray
    kb: np.ndarray
    weight: np.ndarray    # the loss's own weight of each row (multiscale: its full level's)
    difference: np.ndarray  # (A - B) / sqrt 2: its square is the render noise of the row
    ra: np.ndarray        # A - R and B - R: their product is the residual
    rb: np.ndarray
    misfit: np.ndarray    # the mean of the two renders less the reference
    channels: int         # consecutive rows of one pixel, whose noise correlates


def rows(index: int, sensor: Sensor, renders: list[np.ndarray],
         pair: list[list[np.ndarray | None]],
         comps: list[_Component], job: Job, count: int) -> Rows:
    gain = sensor.gain if sensor.gain is not None else np.ones(3)
    a, b = (r * gain for r in renders)
    ref = sensor.reference.astype(np.float64)
    weight = (np.ones_like(ref) if sensor.weight is None
              else sensor.weight.astype(np.float64))
    if job.clamp:  # compared in [0, 1]: a clipped pixel has no slope
        weight = weight * ((a + b) / 2 < 1.0)
        ref = np.clip(ref, 0.0, 1.0)
    estimates = []
    for n, cols in enumerate(pair):
        image = (a, b)[n]
        j = [col * gain if col is not None else
             image * ((np.arange(3) == c.index) & (c.sensor == index))
             for col, c in zip(cols, comps)]
        estimates.append(np.stack(j, axis=-1))  # (H, W, 3, p)
    ja, jb = estimates
    loss = LOSSES[job.loss]
    if loss.images is not None:  # the images as the loss compares them
        ja, jb, a, b, ref = loss.images(ja, jb, a, b, ref, weight)
    # The loss's weight of each row, as losses._mean: sum(w x) / max(sum(w), 1), mean over
    # sensors; a loss may weigh them its own way (multiscale_mse: K = sum_l D_l^T C_l D_l).
    c = weight / max(float(weight.sum()), 1.0) / count
    if loss.weigh is not None:
        ka, kb = (loss.weigh(j, weight) / count for j in (ja, jb))
    else:
        ka, kb = ja * c[..., None], jb * c[..., None]
    p = ja.shape[-1]
    flat = (lambda x: x.reshape(-1, p))
    return Rows(flat(ja), flat(jb), flat(ka), flat(kb), c.ravel(),
                ((a - b) / np.sqrt(2)).ravel(), (a - ref).ravel(), (b - ref).ravel(),
                ((a + b) / 2 - ref).ravel(), a.shape[-1] if a.ndim == 3 else 1)


def linearized(rows: list[Rows], loss: str) -> covariance.Linearized:
    p = rows[0].ja.shape[1]
    h, spread, q, qr = (np.zeros((p, p)) for _ in range(4))
    gradient, gradient_noise = np.zeros(p), np.zeros(p)
    k = LOSSES[loss].step_noise
    for r in rows:
        # 2 K^T (I - R), J's estimates independent of the renders': unbiased
        gradient += (r.ka + r.kb).T @ r.misfit
        # its variance from J's own noise: (ka - kb)^2 estimates that of ka + kb
        gradient_noise += ((r.ka - r.kb) ** 2).T @ r.misfit ** 2
        h += 2 * covariance.crossed(r.ja, r.kb, np.ones(len(r.ja)))[0]
        spread = np.sqrt(spread ** 2 + (2 * covariance.crossed(r.ja, r.jb, r.weight)[1]) ** 2)
        q += k * covariance.per_pixel(r.ka, r.kb, r.difference, r.difference, r.channels)[0]
        qr += 4 * covariance.residual_noise(r.ka, r.kb, r.difference, r.ra, r.rb, r.weight,
                                            r.channels)
    return covariance.Linearized(h, q, qr, spread, gradient, gradient_noise)

"""Image losses. Each maps the renders of one sensor, its reference and a pixel weight (the
reference's mask and alpha weight in [0, 1], 0 where the reference is NaN/Inf) to a scalar
Dr.Jit tensor with gradients. ``renders`` says how many independent renders a loss needs.

Means are weighted: mean_w(x) = sum(w * x) / sum(w), so masked pixels neither count nor
dilute the loss. A reference whose every pixel counts fully has no weight (``None``): its
losses are plain means, one reduction less per iteration.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import drjit as dr
import mitsuba as mi

Tensor = "mi.TensorXf"  # annotations only: the class exists once a variant is set
EPSILON = 1e-3  # keeps brightness normalization finite on black images


@dataclass(frozen=True)
class Loss:
    name: str
    renders: int
    fn: Callable[..., "mi.TensorXf"]  # (renders, reference, weight) -> shape ()
    objective: bool = True  # False: a diagnostic that gradient descent would abuse
    # Iterations over which the loss is averaged before it is compared (best iteration, min
    # error): 1 for losses that are >= 0; more for estimates that noise can push below 0.
    window: int = 1


def _mean(x: Tensor, w: Tensor | None) -> Tensor:
    if w is None:
        return dr.mean(x, axis=None)
    return dr.sum(w * x, axis=None) / dr.maximum(dr.sum(w, axis=None), 1.0)


def _mse(images: list[Tensor], ref: Tensor, w: Tensor) -> Tensor:
    # L2 = mean_w (I - R)^2
    return _mean(dr.square(images[0] - ref), w)


def _dual_buffer(images: list[Tensor], ref: Tensor, w: Tensor) -> Tensor:
    # Deng et al. 2022: with two renders A, B of independent noise,
    #   E[(A - R)(B - R)] = (E[A] - R)^2,
    # so the noise that biases plain MSE at low spp cancels. A single estimate can be < 0.
    return _mean((images[0] - ref) * (images[1] - ref), w)


def _brightness_independent(images: list[Tensor], ref: Tensor, w: Tensor) -> Tensor:
    # MSE of I / (mean I + eps) against R / (mean R + eps): only relative shading matters.
    a = images[0] / (_mean(images[0], w) + EPSILON)
    b = ref / (_mean(ref, w) + EPSILON)
    return _mean(dr.square(a - b), w)


def _mae(images: list[Tensor], ref: Tensor, w: Tensor) -> Tensor:
    return _mean(dr.abs(images[0] - ref), w)


def _mean_bias(images: list[Tensor], ref: Tensor, w: Tensor) -> Tensor:
    return _mean(images[0] - ref, w)


def half(t: Tensor) -> Tensor:
    """2x2 box downsampling of an (H, W, C) tensor (odd rows/columns dropped); differentiable."""
    h, w, c = (int(s) for s in t.shape)
    h2, w2 = h // 2, w // 2
    i = dr.arange(mi.UInt32, h2 * w2 * c)
    ch, rest = i % c, i // c
    x, y = rest % w2, rest // w2
    total = 0
    for dy in (0, 1):
        for dx in (0, 1):
            total += dr.gather(mi.Float, t.array, ((2 * y + dy) * w + 2 * x + dx) * c + ch)
    return mi.TensorXf(total * 0.25, (h2, w2, c))


def _multiscale(images: list[Tensor], ref: Tensor, w: Tensor) -> Tensor:
    # sum over pyramid levels (full, 1/2, 1/4, ... down to 8 px) of the weighted MSE. Coarse
    # levels see low-frequency errors with little noise; the full level keeps detail.
    img, total = images[0], _mse(images, ref, w)
    while min(int(s) for s in img.shape[:2]) >= 16:
        img, ref = half(img), half(ref)
        w = None if w is None else half(w)
        total += _mse([img], ref, w)
    return total


LOSSES = {loss.name: loss for loss in (
    Loss("mse", 1, _mse),
    Loss("dual_buffer", 2, _dual_buffer, window=8),
    Loss("brightness_independent_mse", 1, _brightness_independent),
    Loss("mae", 1, _mae),
    Loss("mean_bias_error", 1, _mean_bias, objective=False),
    Loss("multiscale_mse", 1, _multiscale),
)}

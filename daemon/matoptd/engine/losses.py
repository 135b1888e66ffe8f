"""Image losses, each declared once with everything the daemon needs to know of it: the Dr.Jit
function the loop descends, how many independent renders it takes per sensor (admission
counts them), the window its estimates are averaged over, a line for clients, and the
standard errors' model of it (uncertainty.py asks, never the name).

A loss maps the renders of one sensor, its reference and a pixel weight (the reference's mask
and alpha weight in [0, 1], 0 where the reference is NaN/Inf) to a scalar Dr.Jit tensor with
gradients. Means are weighted: mean_w(x) = sum(w * x) / sum(w), so masked pixels neither
count nor dilute the loss. A reference whose every pixel counts fully has no weight
(``None``): its losses are plain means, one reduction less per iteration.

Adding a loss: write its function here and add a ``Loss`` to ``LOSSES``; give it a value in
the API's ``Loss`` enum (proto/matopt/v1/matopt.proto, LOSS_<NAME>). tests/test_registries.py
holds the two lists together. Dr.Jit is imported inside the functions, so the daemon's own
process reads these declarations without loading the renderer.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

EPSILON = 1e-3  # keeps brightness normalization finite on black images


@dataclass(frozen=True)
class Loss:
    name: str
    title: str                   # one line: what it compares (clients show it)
    fn: Callable                 # (renders, reference, weight) -> Dr.Jit scalar
    renders: int = 1             # independent renders per sensor and iteration
    objective: bool = True       # False: a diagnostic that gradient descent would abuse
    # Iterations over which the loss is averaged before it is compared (best iteration, min
    # error): 1 for losses that are >= 0; more for estimates that noise can push below 0.
    window: int = 1
    # The standard errors' model. ``least_squares`` False: they are the L2 approximation's,
    # and how far Adam's last steps scatter is not modelled. ``step_noise``: k of a step's
    # gradient noise, k (KJ)^T S_r (KJ), 4 for one render, 2 where two renders are averaged.
    least_squares: bool = True
    step_noise: float = 4.0
    # numpy: (ja, jb, a, b, ref, weight) -> the same as the loss compares them (normalized)
    images: Callable | None = None
    # numpy: (j, weight) -> K J, the loss's own weighting of J's rows; None: weight / sum(w)
    weigh: Callable | None = None


def _mean(x, w):
    import drjit as dr
    if w is None:
        return dr.mean(x, axis=None)
    return dr.sum(w * x, axis=None) / dr.maximum(dr.sum(w, axis=None), 1.0)


def _mse(images, ref, w):
    import drjit as dr
    # L2 = mean_w (I - R)^2
    return _mean(dr.square(images[0] - ref), w)


def _dual_buffer(images, ref, w):
    # Deng et al. 2022: with two renders A, B of independent noise,
    #   E[(A - R)(B - R)] = (E[A] - R)^2,
    # so the noise that biases plain MSE at low spp cancels. A single estimate can be < 0.
    return _mean((images[0] - ref) * (images[1] - ref), w)


def _brightness_independent(images, ref, w):
    import drjit as dr
    # MSE of I / (mean I + eps) against R / (mean R + eps): only relative shading matters.
    a = images[0] / (_mean(images[0], w) + EPSILON)
    b = ref / (_mean(ref, w) + EPSILON)
    return _mean(dr.square(a - b), w)


def _mae(images, ref, w):
    import drjit as dr
    return _mean(dr.abs(images[0] - ref), w)


def _mean_bias(images, ref, w):
    return _mean(images[0] - ref, w)


def half(t):
    """2x2 box downsampling of an (H, W, C) tensor (odd rows/columns dropped); differentiable."""
    import drjit as dr
    import mitsuba as mi
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


def _multiscale(images, ref, w):
    # sum over pyramid levels (full, 1/2, 1/4, ... down to 8 px) of the weighted MSE. Coarse
    # levels see low-frequency errors with little noise; the full level keeps detail.
    img, total = images[0], _mse(images, ref, w)
    while min(int(s) for s in img.shape[:2]) >= 16:
        img, ref = half(img), half(ref)
        w = None if w is None else half(w)
        total += _mse([img], ref, w)
    return total


# -- the same on numpy, for the standard errors' linearization ------------------------------

def _normalized(ja, jb, a, b, ref, weight):
    """brightness_independent_mse's images, I / (mean_w I + eps), and J through that map
    (linearized at the mean render)."""
    total = max(float(weight.sum()), 1.0)
    mean = float(np.sum(weight * (a + b) / 2)) / total + EPSILON
    level = (a + b) / 2

    def through(j):
        slope = np.sum(weight[..., None] * j, axis=(0, 1, 2)) / total
        return j / mean - level[..., None] * slope / mean ** 2

    ref_mean = float(np.sum(weight * ref)) / total + EPSILON
    return (through(ja), through(jb), a / (float(np.sum(weight * a)) / total + EPSILON),
            b / (float(np.sum(weight * b)) / total + EPSILON), ref / ref_mean)


def half_array(x: np.ndarray) -> np.ndarray:
    """``half`` on numpy: 2x2 box average over the first two axes, odd ones dropped."""
    h, w = x.shape[0] // 2 * 2, x.shape[1] // 2 * 2
    x = x[:h, :w]
    return 0.25 * (x[0::2, 0::2] + x[1::2, 0::2] + x[0::2, 1::2] + x[1::2, 1::2])


def _half_adjoint(x: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    out = np.zeros(shape + x.shape[2:])
    for dy in (0, 1):
        for dx in (0, 1):
            out[dy:2 * x.shape[0]:2, dx:2 * x.shape[1]:2] = 0.25 * x
    return out


def _pyramid(j: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """K J for multiscale_mse: sum over its levels of D_l^T C_l D_l J (_multiscale)."""
    total = j * (weight / max(float(weight.sum()), 1.0))[..., None]
    levels = [(j, weight)]
    while min(levels[-1][0].shape[:2]) >= 16:
        x, w = levels[-1]
        levels.append((half_array(x), half_array(w)))
        back = levels[-1][0] * (levels[-1][1] / max(float(levels[-1][1].sum()), 1.0))[..., None]
        for finer in reversed(levels[:-1]):
            back = _half_adjoint(back, finer[0].shape[:2])
        total = total + back
    return total


LOSSES = {loss.name: loss for loss in (
    Loss("mse", "mean squared error", _mse),
    Loss("dual_buffer", "two independent renders, mean((a - ref)(b - ref)): render noise does "
         "not bias the optimum (Deng et al. 2022); a single estimate can be negative",
         _dual_buffer, renders=2, window=8, step_noise=2.0),
    Loss("brightness_independent_mse", "MSE after dividing render and reference by their own "
         "means: matches colour and shading, not overall brightness", _brightness_independent,
         images=_normalized),
    Loss("mae", "mean absolute error (L1)", _mae, least_squares=False),
    Loss("mean_bias_error", "mean of render - reference (a diagnostic, not an objective)",
         _mean_bias, objective=False),
    Loss("multiscale_mse", "MSE summed over an image pyramid (full, 1/2, 1/4, ...)",
         _multiscale, weigh=_pyramid),
)}
OBJECTIVES = tuple(name for name, loss in LOSSES.items() if loss.objective)

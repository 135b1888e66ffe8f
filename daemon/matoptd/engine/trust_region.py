"""A damped Gauss-Newton step (Levenberg-Marquardt) in a trust region, and the region's update
from the loss the step led to: pure numpy, for the gauss_newton choice.

The model is L(u + d) ~ L(u) + g.d + d.H.d / 2 with H = 2 J^T C J and g = 2 J^T C (I - R),
both estimated from renders (rows.py): H from two independent estimates of J crossed, so its
entries carry a standard error (``spread``) but no bias. In coordinates y = d / scale (scale:
each component's difference step, so that a log width and an albedo weigh alike) the step is

    y(mu) = -(H_y + mu I)^+ g_y,    the least mu >= 0 with |y(mu)| <= radius,

over the eigen-directions of H_y. A direction whose eigenvalue is within NOISE_LEVELS of its
own standard error (or not positive) is swamped by noise: the images do not say how far to go
along it, so it is damped (``damped``): its curvature is taken as that bound, and a step
along it is no longer than the images vouch for. One singular with no noise (nothing bounds
it) is not stepped. A component at a bound that the gradient pushes past it stays there; the
rest are clipped.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .covariance import NOISE_LEVELS

GROW = 2.0          # the radius after a step the loss confirmed: this times the step's length
SHRINK = 0.5        # ... after a step whose predicted fall the loss did not show
REJECT = 0.25       # ... after a step that made the loss worse (undone)
MIN_RADIUS = 0.05   # in difference steps: below this a step is lost in the noise anyway
MAX_RADIUS = 64.0


@dataclass
class Proposal:
    delta: np.ndarray    # the step in u, within the bounds
    predicted: float     # the fall of the loss the model predicts for it
    length: float        # |delta / scale|
    damped: list[int]    # components whose main direction was not stepped


def step(hessian: np.ndarray, gradient: np.ndarray, spread: np.ndarray, scale: np.ndarray,
         radius: float, u: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> Proposal:
    """The step from ``u`` (each component in [lo, hi])."""
    outer = np.outer(scale, scale)
    h, g, noise = hessian * outer, gradient * scale, spread * outer
    held = ((u <= lo) & (g > 0)) | ((u >= hi) & (g < 0))
    free = np.flatnonzero(~held)
    y, damped = np.zeros(len(u)), []
    if free.size:
        values, vectors = np.linalg.eigh(h[np.ix_(free, free)])
        square = vectors ** 2
        # each eigenvalue's standard error, the entries' errors taken as independent
        error = np.sqrt(np.einsum("ik,ij,jk->k", square, noise[np.ix_(free, free)] ** 2,
                                  square))
        # a direction within its noise of flat is damped: its curvature taken as that bound,
        # so a step along it is no longer than the images can vouch for
        floor = NOISE_LEVELS * error
        damped = sorted({int(free[np.argmax(square[:, k])])
                         for k in np.flatnonzero(values <= floor)})
        curvature = np.maximum(values, floor)
        keep = curvature > 1e-12 * max(curvature.max(), 0.0)  # no bound at all: not stepped
        v, lam = vectors[:, keep], curvature[keep]
        a = v.T @ g[free]
        y[free] = -(v @ (a / lam)) if lam.size else 0.0
        if np.linalg.norm(y) > radius:
            # |y(mu)| falls with mu, and at mu = |a| / radius it is at most radius
            low, high = 0.0, float(np.linalg.norm(a)) / radius
            for _ in range(60):
                mu = (low + high) / 2
                low, high = (mu, high) if np.linalg.norm(a / (lam + mu)) > radius else (low, mu)
            y[free] = -(v @ (a / (lam + high)))
    delta = np.clip(u + scale * y, lo, hi) - u
    predicted = -float(gradient @ delta + delta @ hessian @ delta / 2)
    return Proposal(delta, predicted, float(np.linalg.norm(delta / scale)), damped)


def judge(fell: float, noise: float, predicted: float, length: float, radius: float
          ) -> tuple[bool, float]:
    """Whether a step stands, and the next radius, from how far the loss fell along it
    (``fell``, with standard error ``noise``). A fall beyond the noise: kept, and the radius
    grows past the step. A rise beyond it (or a fall not finite): undone, and the radius
    shrinks below the step. Within the noise the step is kept (it is no worse as far as the
    images tell); the radius shrinks only when the model promised a fall that would have
    shown."""
    if not np.isfinite(fell) or fell < -noise:
        return False, max(MIN_RADIUS, REJECT * length)
    if fell > noise:
        return True, min(MAX_RADIUS, max(radius, GROW * length))
    if predicted > 2 * noise:
        return True, max(MIN_RADIUS, SHRINK * length)
    return True, radius


def fall(before: np.ndarray, after: np.ndarray, noise_before: np.ndarray,
         noise_after: np.ndarray, delta: np.ndarray) -> tuple[float, float]:
    """How far the loss fell along ``delta``, from the gradients at its ends (the trapezoid
    rule: exact for a quadratic), and its standard error from the gradients' covariances."""
    variance = float(delta @ (noise_before + noise_after) @ delta) / 4
    return -float((before + after) @ delta) / 2, float(np.sqrt(max(variance, 0.0)))

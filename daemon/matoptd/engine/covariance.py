"""How far a recovered value may be from the truth: the covariance of what a job ends at, from
its images linearized at a kept iteration. Pure numpy; ``jacobian.py`` and ``uncertainty.py``
make the inputs.

A job minimizes L(u) = sum_i c_i (I_i(u) - R_i)^2 over pixel-channels i (c_i: the loss's
weight of the pixel, its mask over the mask's sum over the sensors) in latent coordinates u
(the values Adam steps on: v, or log v). Near the optimum, with J = dI/du:

    H   = 2 J^T C J                    Gauss-Newton Hessian of L
    Q   = k J^T C S_r C J              covariance of one iteration's gradient: S_r the
                                       render noise at the job's spp, k = 4 for MSE (2 for
                                       dual_buffer, whose two renders halve it)
    Q_R = 4 J^T C S_R C J              the same for the reference's own noise and whatever the
                                       scene does not model (S_R: residual of the mean render)

Two things move the value a job ends at away from the truth:

- The reference: its noise shifts the optimum of L by H^-1 (its gradient), so
  Cov_ref = H^-1 Q_R H^-1, the Gauss-Newton sigma^2 (J^T J)^-1 with per-pixel sigma^2
  (White's sandwich, which also holds when pixels differ in noise).
- Adam: each step sees one render's noise, and the value scatters around the optimum by
  what its last steps have not averaged out. Linearized, m' = b1 m + (1 - b1)(H d + xi) and
  d' = d - D_t m' with D_t = lr_t / ((1 - b1^t) sqrt(v_t)), whose covariance P is carried
  over the job's steps from 0 (its start is not random). v_t is Adam's second moment: the
  noise's own E[g^2] (H P H + Q, from this model) plus what Adam measured beyond it (the
  large gradients of a start far from the optimum, which shrink every later step).

Past a gain D H of 2 a step scatters the value as the fit to the one render it saw,
sigma^2 (J^T J)^-1 with one render's noise (the textbook estimate); real Adam gets no further,
as overshoots inflate v. A long job at a small rate averages many renders and ends far closer
than that: the model follows the job's own schedule. Two figures come from what the job
recorded: Q is scaled to the variance of the gradients of its last steps (the derivative's
own noise adds to the render's), and the Gauss-Newton step H^-1 g of their mean gradient, the
distance a job still converging has left, is added as a bias where it lies beyond what the
scatter and the gradients' own noise explain (a settled job's last steps wander by the
scatter, and adding their mean again counted it twice: standard errors 1.4x too wide).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

BETA_1, BETA_2, EPSILON = 0.9, 0.999, 1e-8  # drjit.opt.Adam's defaults, which optimize.py uses
# A component is not determined when this much of it lies in directions of J^T J that the
# images do not resolve (eigenvalues within the estimate's own noise of 0).
NULL_WEIGHT = 0.05
# How many noise levels of its estimate an eigenvalue of J^T J must exceed to count.
NOISE_LEVELS = 3.0
GAIN = 2.0  # the most a step's gain d H is taken to be (_bounded)
COUPLED = 0.8  # |cosine| of two components' J beyond which they move the render as one


@dataclass
class Linearized:
    """A kept iteration's fit linearized, in latent coordinates (one row/column per
    component). ``hessian`` and ``noise`` come from two independent estimates of J, crossed,
    so neither holds J's own Monte Carlo noise; ``spread`` is the standard error that noise
    leaves in each entry of ``hessian``."""

    hessian: np.ndarray    # H
    noise: np.ndarray      # Q, one iteration's gradient
    reference: np.ndarray  # Q_R
    spread: np.ndarray
    gradient: np.ndarray | None = None  # dL/du, 2 (K J)^T (I - R)
    gradient_noise: np.ndarray | None = None  # the gradient's variance from J's own noise


@dataclass
class Dynamics:
    """What Adam did on the way to the kept iteration, per component (same order)."""

    rates: np.ndarray            # (steps, p): each step's learning rate (schedule applied)
    second_moment: np.ndarray    # (p,): Adam's raw second moment now (before bias correction)
    count: int                   # Adam's step count now (the second moment's age)
    measured: np.ndarray         # (p,): bool, second_moment is the component's own (else
                                 # it is held as given: a texture's mean over its texels)
    gradients: np.ndarray        # (n, p): the gradients of the last steps, NaN where a
                                 # component's were not recorded
    beta_1: np.ndarray | float = BETA_1  # (p,): Adam's first-moment decay per component


def crossed(a: np.ndarray, b: np.ndarray, weight: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The symmetric part of a^T diag(weight) b for two independent estimates a, b (rows x p)
    of one matrix J, and each entry's standard error. E[a^T W b] is J^T W J, without the
    variance that a^T W a would add (which makes J^T J look larger and standard errors
    smaller than they are). Per row, a product of two estimates with noise s^2 = (a - b)^2 / 2
    each varies by J_k^2 s_l^2 + J_l^2 s_k^2 + s_k^2 s_l^2, J^2 estimated by a b."""
    m = (a * weight[:, None]).T @ b
    noise = (a - b) ** 2 / 2
    signal = np.maximum(a * b, 0.0)
    w2 = (weight ** 2)[:, None]
    variance = (w2 * signal).T @ noise + (w2 * noise).T @ signal + (w2 * noise).T @ noise
    return (m + m.T) / 2, np.sqrt(np.maximum(variance, 0))


def per_pixel(ka: np.ndarray, kb: np.ndarray, da: np.ndarray, db: np.ndarray,
              channels: int) -> tuple[np.ndarray, np.ndarray]:
    """J^T S J for a noise S whose channels of one pixel correlate, from two estimates ka, kb
    of J (rows x p, ``channels`` consecutive rows a pixel) and per row two factors whose
    product estimates S per pixel (da db^T: (A - B)/sqrt 2 twice for a render's noise, A - R
    and B - R for the residual); and each diagonal entry's spread over the pixels.

    One path carries all three channels of a sample, so their noise moves together: summed
    over the channels, as a roughness's or eta's J is, a pixel varies by up to 3x the sum of
    its channels' variances. Per row alone, the reference's term of the textured calibration
    case was 1.35x too narrow (Mitsuba's own variance of J R over 40 references: 1.8x the
    per-channel sum)."""
    p = ka.shape[1]
    u = (ka * da[:, None]).reshape(-1, channels, p).sum(axis=1)
    v = (kb * db[:, None]).reshape(-1, channels, p).sum(axis=1)
    m = u.T @ v
    return (m + m.T) / 2, np.sqrt(np.sum((u * v) ** 2, axis=0))


def residual_noise(ka: np.ndarray, kb: np.ndarray, difference: np.ndarray, ra: np.ndarray,
                   rb: np.ndarray, weight: np.ndarray, channels: int) -> np.ndarray:
    """J^T C S_R C J from two estimates of C J (rows x p), the render noise's difference
    (A - B)/sqrt 2 per row and the residuals A - R, B - R of two renders A, B (per_pixel).

    The residual is unbiased per row but, against a reference with 8 times the job's
    samples, some 8 times noisier than its mean: over the few pixels a roughness moves, the
    J-weighted sum's spread between seeds was 2.7 times its mean, and clipped at 0 it made
    standard errors too wide. So the reference's noise is taken as one multiple of the
    render noise over the whole image (a render's noise is a render's at other spp: one
    ratio, from every pixel), unless the per-pixel estimate exceeds that by more than its
    own noise (what the scene does not model, as with a photograph): then it is kept."""
    # each pixel's own square bounds its variance: Monte Carlo noise is heavy-tailed
    pixel, spread = per_pixel(ka, kb, ra, rb, channels)
    w2 = weight ** 2
    ratio = max(float(w2 @ (ra * rb)) / max(float(w2 @ difference ** 2), 1e-300), 0.0)
    pooled = ratio * per_pixel(ka, kb, difference, difference, channels)[0]
    beyond = np.diag(pixel) - np.diag(pooled) > NOISE_LEVELS * spread
    return pixel if beyond.any() else pooled


def determined(hessian: np.ndarray, spread: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[list[int]]]:
    """(mask of the determined components, pseudo-inverse of H over their directions, mask
    of the components whose J was too noisy to tell, the undetermined components grouped by
    the directions they share: components that change the render as one).

    A component whose J^T J is within NOISE_LEVELS standard errors of 0 (or below) is too
    noisy to tell; it is left out, and the others' covariance holds it at its value, unless
    its J and another's are nearly parallel (COUPLED): then neither is determined. H over
    the rest is scaled to a unit diagonal; its eigenvalues within NOISE_LEVELS standard
    errors of 0 (or below) are directions these images do not decide, and a component with
    more than NULL_WEIGHT of itself in them is not determined."""
    p = len(hessian)
    diagonal = np.diag(hessian)
    # a column that is 0 without noise (nothing in view depends on it) is not noisy: the
    # render does not change with it
    noisy = (diagonal <= NOISE_LEVELS * np.diag(spread)) & (np.diag(spread) > 0)
    inverse = np.zeros((p, p))
    ok = np.zeros(p, dtype=bool)
    idx = np.flatnonzero(~noisy & (diagonal > 0))
    groups = [[int(k)] for k in np.flatnonzero(~noisy & (diagonal <= 0))]
    if not idx.size:
        return ok, inverse, noisy, groups
    scale = 1 / np.sqrt(diagonal[idx])
    h = hessian[np.ix_(idx, idx)] * np.outer(scale, scale)
    error = spread[np.ix_(idx, idx)] * np.outer(scale, scale)
    values, vectors = np.linalg.eigh(h)
    # each eigenvalue v^T H v against its own standard error, sqrt(sum (v_k v_l e_kl)^2)
    noise = np.sqrt(np.einsum("kj,lj,kl->j", vectors ** 2, vectors ** 2, error ** 2))
    null = values <= np.maximum(NOISE_LEVELS * noise, 1e-9 * max(values.max(), 1e-30))
    weight = np.sum(vectors[:, null] ** 2, axis=1)
    ok[idx] = weight <= NULL_WEIGHT
    kept = vectors[:, ~null]
    inner = (kept / values[~null]) @ kept.T
    inverse[np.ix_(idx, idx)] = inner * np.outer(scale, scale)
    found = [{int(idx[k]) for k in np.flatnonzero(vectors[:, j] ** 2 > NULL_WEIGHT)}
             for j in np.flatnonzero(null)]
    # A component too noisy to tell that moves the render as a determined one does (a light
    # whose radiance scales the image as a gain does) leaves that one's value undecided too:
    # held at its value, the other would look determined when only their product is.
    for k in np.flatnonzero(noisy):
        cosine = np.abs(hessian[k, idx]) / np.sqrt(
            np.maximum(diagonal[k], 1e-300) * diagonal[idx])
        coupled = idx[(np.minimum(cosine, 1.0) > COUPLED)
                      & (np.abs(hessian[k, idx]) > NOISE_LEVELS * spread[k, idx])]
        if coupled.size:
            ok[coupled] = False
            noisy[k] = False
            found.append({int(k), *map(int, coupled)})
    for group in found:  # merged where they share a component
        for other in [g for g in groups if group & set(g)]:
            group |= set(other)
            groups.remove(other)
        groups.append(sorted(group))
    return ok, inverse, noisy, groups


def positive(m: np.ndarray) -> np.ndarray:
    """m with its negative eigenvalues set to 0: an estimate of a covariance (or of J^T J)
    from noisy products can come out indefinite where its true value is near singular."""
    values, vectors = np.linalg.eigh((m + m.T) / 2)
    return (vectors * np.maximum(values, 0)) @ vectors.T


def adam_scatter(hessian: np.ndarray, noise: np.ndarray, dynamics: Dynamics,
                 passes: int = 3) -> np.ndarray:
    """Covariance of where Adam's last step leaves the value around the optimum (the model
    in the module's docstring), carried over ``dynamics.rates``.

    Adam's v at each step is the model's own E[g^2] plus the excess Adam measured beyond it
    (``second_moment`` minus the model's value at ``count``), found by a few passes."""
    p = len(hessian)
    eye = np.eye(p)
    beta_1 = np.broadcast_to(np.asarray(dynamics.beta_1, np.float64), (p,))
    b1 = np.diag(beta_1)
    excess = np.zeros(p)
    fixed = dynamics.second_moment / (1 - BETA_2 ** max(dynamics.count, 1))
    covariance = np.zeros((2 * p, 2 * p))
    for _ in range(passes):
        covariance = np.zeros((2 * p, 2 * p))
        raw, g2 = np.zeros(p), np.diag(noise).copy()
        for t, rate in enumerate(dynamics.rates, 1):
            g2 = np.diag(hessian @ covariance[:p, :p] @ hessian) + np.diag(noise)
            raw = BETA_2 * raw + (1 - BETA_2) * g2
            v = np.where(dynamics.measured, (raw + excess) / (1 - BETA_2 ** t), fixed)
            d = np.diag(_bounded(rate / ((1 - beta_1 ** t) * (np.sqrt(np.maximum(v, 0))
                                                              + EPSILON)), hessian))
            # m' = b1 m + (1 - b1) g, d' = d - D m', per component's b1
            a = np.block([[eye - d @ (eye - b1) @ hessian, -d @ b1],
                          [(eye - b1) @ hessian, b1]])
            b = np.vstack([-d @ (eye - b1), eye - b1])
            covariance = a @ covariance @ a.T + b @ noise @ b.T
        # The noise alone up to Adam's count (steps after the kept iteration included)
        for _ in range(len(dynamics.rates), dynamics.count):
            raw = BETA_2 * raw + (1 - BETA_2) * g2
        excess = np.maximum(dynamics.second_moment - raw, 0)
    return covariance[:p, :p]


def _bounded(d: np.ndarray, hessian: np.ndarray) -> np.ndarray:
    """Adam's step sizes with the gain D H kept at or below GAIN.

    Linearized with momentum b1 = 0.9, a step of gain x = d H leaves a stationary scatter of
    about x / 2 times one render's Q / H^2, and grows without bound past x = 38. Real Adam
    never gets there: a step that overshoots makes the next gradients large, v grows with
    them and the steps shrink back. So the gain stops where the scatter is that of a fit to
    the render a step saw (x = 2), first per component, then along any direction of H."""
    scale = np.sqrt(np.maximum(np.diag(hessian), 0))
    d = np.minimum(d, GAIN / np.maximum(scale ** 2, 1e-300))
    root = np.sqrt(d)
    largest = np.linalg.eigvalsh(root[:, None] * hessian * root[None, :]).max(initial=0)
    return d * min(1.0, GAIN / largest) if largest > 0 else d


def gradient_noise(model: np.ndarray, hessian: np.ndarray, scatter: np.ndarray,
                   gradients: np.ndarray, least: int = 8) -> np.ndarray:
    """Q with its diagonal set to what the job's own gradients showed.

    Q from J and the render noise leaves out the noise of the derivative estimate itself
    (prb's derivative image at 16 spp is about as noisy as its render, which doubles the
    gradient's variance on a Cornell box). The recorded gradients of the last steps, less a
    straight line (the drift of a job still converging) and less what the scatter itself
    contributes (H P H), measure the whole; Q keeps its correlations and is scaled to it,
    never below the model. Components with fewer than ``least`` recorded gradients take the
    median scale of the others (1 when none has enough); one whose modelled noise is not
    positive (a J too noisy to cross) takes its measured variance, uncorrelated."""
    model = positive(model)
    p = len(model)
    measured = np.full(p, np.nan)
    steps = np.arange(len(gradients), dtype=np.float64)
    for k in range(p):
        g = gradients[:, k]
        ok = np.isfinite(g)
        if ok.sum() < least:
            continue
        x = np.vstack([np.ones(ok.sum()), steps[ok]]).T
        residual = g[ok] - x @ np.linalg.lstsq(x, g[ok], rcond=None)[0]
        measured[k] = residual @ residual / (ok.sum() - 2) - (hessian @ scatter @ hessian)[k, k]
    diagonal = np.diag(model)
    scaled = np.isfinite(measured) & (diagonal > 1e-12 * max(diagonal.max(), 1e-300))
    ratio = np.full(p, np.nan)
    ratio[scaled] = measured[scaled] / diagonal[scaled]
    known = ratio[scaled]
    ratio = np.where(np.isfinite(ratio), ratio, np.median(known) if known.size else 1.0)
    scale = np.sqrt(np.maximum(ratio, 1.0))
    out = model * np.outer(scale, scale)
    for k in np.flatnonzero(np.isfinite(measured) & ~scaled):
        out[k, :] = out[:, k] = 0.0
        out[k, k] = max(measured[k], 0.0)
    return out


@dataclass
class Estimate:
    covariance: np.ndarray  # latent coordinates; rows of undetermined components are 0
    determined: np.ndarray  # bool per component
    noisy: np.ndarray       # bool per component: not determined as its J was too noisy
    noise: np.ndarray       # the covariance less the remaining distance (a bias, whose
                            # rank one would make every pair look perfectly correlated)
    groups: list[list[int]]  # undetermined components that change the render as one


def estimate(fit: Linearized, dynamics: Dynamics | None) -> Estimate:
    """Cov = Adam's scatter + H^-1 Q_R H^-1 + the remaining distance's b b^T (if any), over the
    determined components; without ``dynamics`` (a loss Adam's model does not hold for) the
    scatter is that of a fit to one render, H^-1 Q H^-1, and there is no b."""
    ok, inverse, noisy, groups = determined(fit.hessian, fit.spread)
    reference = positive(inverse @ fit.reference @ inverse)
    bias = np.zeros_like(reference)
    if dynamics is None or not len(dynamics.rates):
        scatter = inverse @ fit.noise @ inverse
    else:
        hessian = positive(fit.hessian)
        first = adam_scatter(hessian, fit.noise, dynamics)
        noise = gradient_noise(fit.noise, hessian, first, dynamics.gradients)
        scatter = adam_scatter(hessian, noise, dynamics)
        step, n = remaining(inverse, dynamics.gradients)
        if n:
            # A converged job's b is where its last steps wandered (the scatter, which
            # Adam's small last rates barely move) plus the noise of n gradients: only what
            # b shows beyond both is a distance still to go.
            converged = scatter + inverse @ noise @ inverse / n
            if _beyond(step, converged):
                bias = positive(np.outer(step, step) - converged)
    mask = np.outer(ok, ok)
    return Estimate((scatter + reference + bias) * mask, ok, noisy, (scatter + reference) * mask,
                    groups)


def _beyond(step: np.ndarray, covariance: np.ndarray, z: float = 2.326) -> bool:
    """Whether ``step`` lies beyond what ``covariance`` explains at the 99% level: its
    squared Mahalanobis length against chi^2 with p degrees of freedom (Wilson-Hilferty)."""
    p = int(np.count_nonzero(np.diag(covariance) > 0))
    if not p:
        return False
    length = float(step @ np.linalg.pinv(covariance) @ step)
    return length > p * (1 - 2 / (9 * p) + z * np.sqrt(2 / (9 * p))) ** 3


def remaining(inverse: np.ndarray, gradients: np.ndarray, least: int = 8
              ) -> tuple[np.ndarray, int]:
    """How far the last steps' mean value still was from the optimum: the Gauss-Newton step
    H^-1 g of their mean gradient, and how many steps that mean is over. A job that has
    converged has a mean gradient near 0 (its gradients only jitter); one still on its way
    has not, and this is the bias its scatter does not cover. Components with fewer than
    ``least`` recorded gradients count as 0 (and n as 0 when none has enough)."""
    counts = np.sum(np.isfinite(gradients), axis=0)
    counted = counts >= least
    if not counted.any():
        return np.zeros(len(inverse)), 0
    mean = np.where(counted, np.nanmean(np.where(counted, gradients, 0.0), axis=0), 0.0)
    return inverse @ mean, int(counts[counted].min())


def correlated(covariance: np.ndarray, ok: np.ndarray, names: list[str],
               threshold: float = 0.8) -> list[tuple[str, str, float]]:
    """(a, b, correlation) of the determined component pairs with |correlation| above
    ``threshold``, strongest first."""
    sd = np.sqrt(np.maximum(np.diag(covariance), 0))
    out = []
    for i in range(len(names)):
        for j in range(i + 1, len(names)):
            if ok[i] and ok[j] and sd[i] > 0 and sd[j] > 0:
                r = covariance[i, j] / (sd[i] * sd[j])
                if abs(r) > threshold:
                    out.append((names[i], names[j], float(r)))
    return sorted(out, key=lambda x: -abs(x[2]))

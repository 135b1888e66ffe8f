"""How far an estimate is from a known true value (synthetic cases with ground truth).

Pure numpy, shared by the engine (which fills ``ParameterError`` every iteration) and the
unit tests. Values are flat, in Mitsuba's order; ``channels`` is the length of a texture's or
grid's last axis, so that channel c is every ``channels``-th component starting at c.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np


@dataclass
class ParameterError:
    max_abs: float   # largest |estimate - truth| over components
    rmse: float      # over components
    relative: float  # rmse / rms(truth), or rmse when the truth is 0
    psnr: float      # dB, 20 log10(peak / rmse); see ``psnr``
    correlation: list[float] = field(default_factory=list)  # per channel (textures, grids)


def psnr(rmse: float, truth: np.ndarray) -> float:
    """20 log10(peak / rmse) in dB, with peak the truth's largest |component| (1 when the
    truth is all 0, as for an image in [0, 1]); +inf when the estimate is exact."""
    peak = float(np.max(np.abs(truth))) if truth.size else 0.0
    if rmse <= 0:
        return math.inf
    return 20.0 * math.log10((peak if peak > 0 else 1.0) / rmse)


def correlation(value: np.ndarray, truth: np.ndarray, channels: int) -> list[float]:
    """Pearson's r between truth and estimate, per channel over the texels or voxels: 1 when
    the estimate has the truth's pattern (whatever its scale and offset), ~0 when it has none.
    NaN for a channel where either side is constant (no pattern to compare)."""
    v = value.astype(np.float64).reshape(-1, channels)
    t = truth.astype(np.float64).reshape(-1, channels)
    out = []
    for c in range(channels):
        dv, dt = v[:, c] - v[:, c].mean(), t[:, c] - t[:, c].mean()
        norm = math.sqrt(float(np.sum(dv * dv)) * float(np.sum(dt * dt)))
        out.append(float(np.sum(dv * dt)) / norm if norm > 0 else math.nan)
    return out


def parameter_error(value: np.ndarray, truth: np.ndarray, channels: int = 0
                    ) -> ParameterError:
    """All the figures at once; ``channels`` > 0 (a texture or grid) adds the correlations."""
    d = value.astype(np.float64) - truth
    rmse = float(np.sqrt(np.mean(d * d)))
    scale = float(np.sqrt(np.mean(truth.astype(np.float64) ** 2)))
    corr = (correlation(value, truth, channels)
            if channels > 0 and truth.size % channels == 0 else [])
    return ParameterError(float(np.max(np.abs(d))), rmse, rmse / scale if scale > 0 else rmse,
                          psnr(rmse, truth), corr)

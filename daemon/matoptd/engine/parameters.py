"""What a scene's differentiable parameters are: kind, shape, legal range, learning rate, and
conversion between Mitsuba values and the API's flat float lists.

Ranges follow physical validity, keyed by the property name (the last component of the key
that is not ``value`` or ``data``): reflectances and weights live in [0, 1], an index of
refraction of a dielectric stays above 1, radiance and extinction are non-negative and
unbounded. Flat lists follow ``dr.ravel`` order (RGB interleaved per entry) so that a value
read by ``flat()`` and written back by ``assign()`` is the same value.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from ..engine_api import SMALL, ParameterInfo

INF = math.inf
# Adam's default learning rates. A scalar or RGB parameter with a finite range, or optimized in
# log space, gets 0.1: on the thesis's Table 2 case (bench/quality.py) the thesis's 0.03 spends
# hundreds of iterations drifting along the valley where base_color and spec_trans trade off
# (Adam's noise-dominated step is about lr * signal / noise), and 0.1 with the cosine decay and
# 16 spp reaches 2% in a third of the time. The others keep the thesis's 0.03: unbounded ones
# (vertex positions) move in scene units, where 0.1 is a large step for a small object (a
# mesh under large steps takes a share of its extent instead: choices/large_steps.py); each
# texel, voxel or vertex of a large parameter is seen by few pixels, so its gradient is noisy
# and a large rate lets the weakly seen ones wander (a grid's interior voxels); and a medium's
# properties reach the image through scattering, whose gradients are the noisiest of all: on
# the thesis's Table 4 case 0.1 left sigma_t 31% off where 0.03 came within 4%.
DEFAULT_LEARNING_RATE = 0.1
CAUTIOUS_LEARNING_RATE = 0.03
# A dielectric's eta gets 0.01, the thesis's own choice (0.003-0.01): reflection (Fresnel) and
# the refracted image change far faster with eta than the image with a reflectance, and eta
# trades off against base_color and spec_trans. On the thesis's Table 2 case (roughness 0.01),
# eta at 0.1 wandered to 2.3 and dragged roughness up to 0.8 to compensate, and at 0.03 one
# seed of two diverged; at 0.01 both ended within 1% on base_color, spec_trans and eta.
ETA_LEARNING_RATE = 0.01
# Textures and grids of more than SMALL entries get 0.01: Adam's step is about lr per texel
# whatever the gradient's size, so a texel that few pixels see random-walks by ~lr * sqrt(n).
# On the thesis's Table 3 kind (16x16 texture, 32 px, 60 iterations, 4 seeds) the texture's
# PSNR against the truth ended at 13.0-13.9 dB at 0.01 and 9.7-11.0 dB at 0.03.
TEXTURE_LEARNING_RATE = 0.01
# Those stepped in log space (positive, unbounded: a medium's extinction grid) get a relative
# step instead, and 1% a step could not reach a truth 50x above its start (ln 50 = 3.9 takes
# ~390 such steps): 0.2 covers it in about 36 iterations under the cosine decay, which ends
# at 2% a step. An 8^3 extinction grid from 0.002 under a truth of mean 0.1, 60 iterations,
# 3 seeds: its mean ended at 0.093-0.096 (at 0.01: 0.0025), its RMSE 0.046 against the plain
# loop's 0.066 (bench/grids.py).
GRID_LOG_LEARNING_RATE = 0.2
_MEDIUM = {"albedo", "sigma_t", "sigma_a", "sigma_s", "density"}

# An eta of exactly 1 makes a dielectric interface vanish (no gradient, divisions by eta - 1).
ETA_MIN = 1.001
# The principled BSDF uses alpha = max(0.001, roughness^2): below ~0.0316 its specular lobe
# stops changing and its gradient is exactly 0. A principled roughness is therefore rendered
# and reported at no less than ROUGHNESS_FLOOR (0.0318^2 = 0.00101, within 1.2% of the floor in
# alpha), while the value Adam steps on may go on down to ROUGHNESS_MIN (alpha 1e-4, the
# microfacet clamp) and is steered there by the floor's gradient (optimize.py, _value).
# A hard bound at the floor would reflect: a step down clipped, one up not, so on the level
# loss of a near-specular truth noise walks it away; below the floor the walk is free. The
# price: a truth just above the floor that the images hardly show can end there too
# (docs/benchmarks.md, Table 2).
ROUGHNESS_MIN = 0.01
ROUGHNESS_FLOOR = 0.0318
# Microfacet widths are optimized as u = log(v): near a specular truth (alpha 0.001-0.01) a
# linear step of 0.1 is ten times the value and noise kicks it between the floor and 0.3;
# in log space a step changes the width by ~10% at any scale. A width whose range starts at 0
# (a microfacet alpha) is floored at Mitsuba's own clamp, 1e-4.
_WIDTHS = {"roughness", "alpha", "alpha_u", "alpha_v"}
WIDTH_FLOOR = 1e-4
# Their default rate: a 20% change per step at full rate, so that a width can cross the
# decades from a rough start (0.5) to a near-specular truth (0.001) in the first half of a
# 60-iteration job under the cosine decay (at 0.1, alpha 0.5 -> 0.001 stopped at 0.1).
WIDTH_LEARNING_RATE = 0.2

_UNIT = {"reflectance", "base_color", "albedo", "diffuse_reflectance", "specular_reflectance",
         "specular_transmittance", "transmittance", "roughness", "alpha", "alpha_u", "alpha_v",
         "spec_trans", "metallic", "specular", "sheen", "sheen_tint", "spec_tint", "clearcoat",
         "clearcoat_gloss", "flatness", "anisotropic", "opacity", "weight", "diff_trans",
         "vertex_color", "color"}
# Colours that tint the lobes of other parameters. Started black, they make every lobe they
# tint black, and what those lobes carry (spec_trans, eta, a medium's density) gets no
# gradient: on the thesis's Table 3 kind, spec_trans went 0.1 -> 0 in 5 iterations from a black
# texture and stayed there; from mid-grey it reached the truth, 1.0, by iteration 15.
TINTS = {"reflectance", "base_color", "albedo", "diffuse_reflectance", "specular_reflectance",
         "specular_transmittance", "transmittance", "color"}
NEUTRAL_START = 0.5
_NON_NEGATIVE = {"radiance", "irradiance", "intensity", "sigma_t", "sigma_a", "sigma_s",
                 "scale", "k", "density"}


@dataclass(frozen=True)
class Info:
    key: str
    kind: str  # one of engine_api.KINDS
    shape: tuple[int, ...]
    lo: float
    hi: float
    discontinuous: bool


def property_name(key: str) -> str:
    parts = [p for p in key.split(".") if p not in ("value", "data")]
    return parts[-1] if parts else key


def medium_property(key: str) -> bool:
    """A participating medium's albedo, extinction or density."""
    return property_name(key) in _MEDIUM


def homogeneous_medium_property(key: str, kind: str) -> bool:
    """A constant volume's albedo or extinction (one value or colour; a grid's kind is
    volume_grid)."""
    return medium_property(key) and kind in ("scalar", "rgb")


def medium_pairs(records) -> list[str]:
    """The keys of every homogeneous medium whose albedo and sigma_t are both selected, neither
    given a rate (``records``: key -> ParamRecord). The pair share a valley (a darker albedo
    and a thinner medium look alike), which is what the choices that take them mean."""
    pairs: dict[str, list[str]] = {}  # the medium's key prefix -> its selected pair
    for k, r in records.items():
        name = property_name(k)
        if (name in ("albedo", "sigma_t") and r.scene is not None and not r.rate_given
                and homogeneous_medium_property(k, r.kind)):
            pairs.setdefault(k[:k.rindex(name)], []).append(k)
    return [k for keys in pairs.values() if len(keys) == 2 for k in keys]


def dielectric_eta(key: str) -> bool:
    """`obj.eta` is a dielectric's or the principled BSDF's relative IOR; a conductor's complex
    IOR is a texture (`obj.eta.value`) and only needs to be non-negative."""
    return key == "eta" or key.endswith(".eta")


def microfacet_widths(eta_key: str, keys) -> list[str]:
    """The keys of the microfacet width beside a dielectric's eta (the principled BSDF's
    roughness, a rough dielectric's alpha or alpha_u/alpha_v); none for a smooth dielectric."""
    base = eta_key[:-len("eta")]
    for names in (["roughness"], ["alpha"], ["alpha_u", "alpha_v"]):
        found = [k for n in names for k in (base + n, base + n + ".value", base + n + ".data")
                 if k in keys]
        if found:
            return found
    return []


def microfacet_alpha(key: str, value: np.ndarray) -> float:
    """The GGX/Beckmann alpha a width shows (its mean if textured): the principled BSDF's
    roughness r shows as alpha = max(0.001, r^2)."""
    v = float(np.mean(value)) if np.size(value) else 0.0
    return max(0.001, v * v) if property_name(key) == "roughness" else v


def near_specular(widths: dict[str, np.ndarray], current: dict[str, np.ndarray],
                  below: float) -> bool:
    """Whether every width beside an eta shows alpha below ``below`` (a smooth dielectric
    has none: always). ``widths`` holds the scene's values; an optimized width is read from
    ``current`` (theta_i), so an eta switches to differences as its surface sharpens."""
    return all(microfacet_alpha(w, current.get(w, fixed)) < below
               for w, fixed in widths.items())


def legal_range(key: str) -> tuple[float, float]:
    name = property_name(key)
    if dielectric_eta(key):
        return ETA_MIN, 4.0
    if name == "eta":
        return 0.0, INF
    if name == "roughness":
        return ROUGHNESS_MIN, 1.0
    if name in _UNIT:
        return 0.0, 1.0
    if name in _NON_NEGATIVE:
        return 0.0, INF
    if name == "g":
        return -0.999, 0.999
    return -INF, INF


def shown_floor(key: str, lo: float) -> float:
    """The least value a parameter with range minimum ``lo`` is rendered and reported at (0:
    none): a principled roughness whose range reaches below ROUGHNESS_FLOOR shows as it."""
    return ROUGHNESS_FLOOR if property_name(key) == "roughness" and lo <= ROUGHNESS_FLOOR else 0.0


def black_tint(key: str, start: np.ndarray) -> bool:
    """Whether ``start`` is a black tint (every component 0), which starts at NEUTRAL_START."""
    return property_name(key) in TINTS and start.size > 0 and not np.any(start)


def log_space(key: str, lo: float, hi: float) -> bool:
    """Whether the optimizer steps in u = log(v): values positive and unbounded above
    (radiance, extinction: a step is the same relative change at any scale) and microfacet
    widths (roughness, alpha)."""
    return (lo == 0.0 and math.isinf(hi)) or (property_name(key) in _WIDTHS and hi > 0)


def homogeneous_extinction(key: str, size: int) -> bool:
    """A homogeneous medium's scalar sigma_t (a constant volume's one value), which the
    linear_extinction choice steps linearly rather than in log space."""
    return property_name(key) == "sigma_t" and size == 1


def log_bounds(key: str, lo: float, hi: float) -> tuple[float, float]:
    """The range in which a log-space value is kept: the width floor where lo is 0."""
    floor = WIDTH_FLOOR if property_name(key) in _WIDTHS else 0.0
    return max(lo, floor), hi


def kind_and_shape(key: str, value) -> tuple[str, tuple[int, ...]] | None:
    """The API kind of a traversed value, or None when it cannot be optimized."""
    if not (dr.is_diff_v(value) and dr.is_float_v(value)):
        return None  # Python scalars, ScalarVector2u film sizes, integer arrays, 8-bit textures
    if dr.is_tensor_v(value):
        shape = tuple(int(s) for s in value.shape)
        return ("volume_grid" if len(shape) == 4 else "texture"), shape
    if dr.is_matrix_v(value):
        return "transform", (4, 4)
    name = type(value).__name__
    if name.startswith("Color") or (dr.depth_v(value) > 1 and len(value) == 3
                                    and dr.width(value) == 1):
        return "rgb", (3,)
    width = dr.width(value) * (len(value) if dr.depth_v(value) > 1 else 1)
    if "vertex" in key:
        return "vertex_array", (width,)
    return ("scalar", ()) if width == 1 else ("vector", (width,))


def describe(params: mi.SceneParameters) -> list[Info]:
    """The differentiable parameters of a traversed scene, in traversal order."""
    infos = []
    for key in params.keys():
        flags = params.flags(key)
        if flags & int(mi.ParamFlags.NonDifferentiable) or flags & int(mi.ParamFlags.ReadOnly):
            continue
        ks = kind_and_shape(key, params[key])
        if ks is None:
            continue
        lo, hi = legal_range(key)
        infos.append(Info(key, ks[0], ks[1], lo, hi,
                          bool(flags & int(mi.ParamFlags.Discontinuous))))
    return infos


def flat(value) -> np.ndarray:
    """A Mitsuba value as a flat float32 array."""
    if dr.is_tensor_v(value):
        return np.asarray(value, dtype=np.float32).ravel()
    return np.asarray(dr.ravel(dr.detach(value)), dtype=np.float32).ravel()


def assign(template, values: np.ndarray):
    """A value of the template's type (and shape) holding ``values`` (flat, ravel order)."""
    values = np.asarray(values, dtype=np.float32).ravel()
    expected = int(np.prod(template.shape)) if dr.is_tensor_v(template) else len(flat(template))
    if values.size != expected:
        raise ValueError(f"expected {expected} values, got {values.size}")
    # Computed from the array, not its memory mapped: mapped memory is aligned or not by
    # chance, and a frozen function records again whenever that changes (x * 1 + 0 is x).
    owned = dr.fma(mi.Float(values), dr.opaque(mi.Float, 1.0), 0.0)
    if dr.is_tensor_v(template):
        return type(template)(owned, template.shape)
    return dr.unravel(type(template), owned)


def default_learning_rate(info: Info) -> float:
    if dielectric_eta(info.key):
        return ETA_LEARNING_RATE
    if property_name(info.key) in _WIDTHS:
        return WIDTH_LEARNING_RATE
    if info.kind in ("texture", "volume_grid") and math.prod(info.shape) > SMALL:
        return (GRID_LOG_LEARNING_RATE if log_space(info.key, info.lo, info.hi)
                else TEXTURE_LEARNING_RATE)
    bounded = math.isfinite(info.lo) and (math.isfinite(info.hi) or info.lo == 0.0)
    small = info.kind in ("scalar", "rgb")
    medium = medium_property(info.key)
    return DEFAULT_LEARNING_RATE if bounded and small and not medium else CAUTIOUS_LEARNING_RATE


def listing(info: Info, value) -> ParameterInfo:
    """The parameter as the daemon lists it: the value only when it is small."""
    v = flat(value)
    return ParameterInfo(info.key, info.kind, list(info.shape),
                         v.tolist() if v.size <= SMALL else [], info.lo, info.hi,
                         default_learning_rate(info), info.discontinuous)

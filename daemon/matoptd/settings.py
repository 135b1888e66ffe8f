"""What a job is asked to do: its scene, references and parameters, and every setting with its
default, declared once, here.

The API's JobSpec becomes a ``JobSettings`` once, at the edge (``server/job_spec.py``), where
what the request leaves out takes these defaults; from then on it travels as it is: the store
keeps it (JSON), the scheduler and the lanes hand it on, and a worker's engine reads it. The
daemon's answer (``Job.spec``) is built back from it, so a client learns there what was
applied. Defaults that depend on the scene, a parameter's range and learning rate, come from
its listing (``engine_api.ParameterInfo``), which the engine made when the scene was created.

Inputs are named by content, as everything that crosses to a worker is (``engine_api``): files
and large values by SHA-256 digest, which the worker fetches, small values inline. Pure data
and numpy: both processes import it.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

# Names as the API spells them (lower case of its enums' short names); the losses are
# declared with their properties in engine/losses.py (LOSSES).
SCHEDULES = ("cosine", "constant")
SENSOR_MODES = ("accumulate", "step_per_sensor")
# Mitsuba's differentiable integrators a job renders with: the scene's own when it is one of
# them and can differentiate the job's parameters, else one chosen for it (engine/integrator).
INTEGRATORS = ("prb", "prb_basic", "prbvolpath", "prb_projective", "direct_projective")

# The engine's named choices: the special cases of its one optimization loop, each of which a
# job may turn off (JobSettings.choices, NAME -> "off"; "all" stands for every one). Those a
# setting asks for (exposure gains by fit_exposure, smoothness by a weight, large steps by a
# lambda) follow that setting and are not named here. The engine's registry (engine/choices)
# holds exactly these.
CHOICES = {
    "filter_scaling": "a sensor's gaussian or tent filter scaled with a film resized by "
                      "resolution, so renders blur as the references made at the scene's size",
    "depth": "an unbounded or large max_depth cut to the least depth whose cut changes the "
             "image less than the Monte Carlo noise the job averages (measured at its start)",
    "black_start": "a colour that tints other lobes, started black, starts at 0.5 instead",
    "log_space": "positive unbounded values and microfacet widths stepped as u = log v: a "
                 "rate is a relative step",
    "linear_extinction": "a homogeneous medium's scalar sigma_t stepped linearly (not in log "
                         "space), its rate a share of the larger of its value and its start",
    "slow_interface_width": "the microfacet width of a dielectric around a homogeneous medium, "
                            "given no rate, stepped at half its listed rate, so that eta moves "
                            "while the interface is rough; off unless turned on",
    "medium_constant_rate": "a homogeneous medium's albedo and extinction, both selected and "
                            "given no rate, stepped at their full rate to the end (the "
                            "schedule's decay not applied to them; a value of settle: at "
                            "their full rate while they move steadily, at a shrinking share "
                            "of it once they jitter)",
    "medium_damping": "Adam's beta_1 at 0.5 in place of 0.9 in a job that selects a homogeneous "
                      "medium's albedo and extinction, both given no rate (Dr.Jit's is per "
                      "optimizer: every variable of the job), so the pair does not swing along "
                      "the valley it shares, the pair on the schedule in place of "
                      "medium_constant_rate's full rate (a value of settle: at its full rate "
                      "while it moves steadily, then on the schedule from there); off unless "
                      "turned on",
    "roughness_constant_rate": "a principled roughness beside a selected eta, given no rate, "
                               "stepped at its full rate to the end (a value of settle: "
                               "while it moves steadily); off unless turned on",
    "roughness_floor": "a principled roughness rendered at no less than its alpha floor "
                       "(0.0318) while Adam steps on below it",
    "multires": "textures and grids optimized coarse to fine (a value of nearest or linear "
                "upsampling, optionally :LEVELS, e.g. linear:3, sets how)",
    "large_steps": "vertex positions of a mesh of more than 21 vertices stepped as u = (I + "
                   "lambda L) v (Nicolet et al. 2021), lambda and a rate not given chosen from "
                   "the mesh; JobSpec.large_steps_lambda sets lambda",
    "eta_differences": "a dielectric's eta differentiated by central differences of the "
                       "images while its surface is near-specular (a value of quarter or "
                       "full sets the spp of the two sides: a quarter of the job's, the "
                       "default, or all of it; optionally :ALPHA, the width below which "
                       "they apply, e.g. quarter:0.05)",
    "eta_hold": "a dielectric's eta held at its start while the other parameters still move "
                "steadily",
    "gauss_newton": "a handful of scalars and colours stepped by damped Gauss-Newton in a "
                    "trust region (J from two independent estimates) in place of Adam; off "
                    "unless turned on",
    "frozen": "each iteration's render, loss and backward pass recorded once and replayed "
              "(dr.freeze), and so are eta's difference renders and the standard errors' "
              "passes: no Python tracing per iteration; same results",
}
# Choices a job turns on by name (or with ALL_CHOICES): candidates until the matrix decides.
OFF_UNLESS_NAMED = ("gauss_newton", "medium_damping", "roughness_constant_rate",
                    "slow_interface_width")
CHOICE_VALUES = ("on", "off")  # what JobSettings.choices accepts for each name
ALL_CHOICES = "all"            # the key that stands for every name
UPSAMPLING = ("nearest", "linear")
MAX_STARTS = 8  # the most starts a job may compare (JobSettings.starts)


def coarse_to_fine(value: str) -> tuple[str, int]:
    """multires's value as (upsampling, levels): "on" or one of UPSAMPLING, optionally with
    ":LEVELS" (the finest LEVELS of the halvings, the full resolution among them; 0: as many
    as the size allows). ValueError saying what it may be."""
    mode, _, count = value.partition(":")
    mode = UPSAMPLING[0] if mode == "on" else mode
    if mode not in UPSAMPLING or (count and not (count.isdigit() and int(count) >= 1)):
        raise ValueError(f"choice 'multires' cannot be '{value}': give on, off, "
                         f"{' or '.join(UPSAMPLING)}, optionally with :LEVELS (a whole number "
                         ">= 1, e.g. linear:3)")
    return mode, int(count or 0)


DIFFERENCE_SPP = {"quarter": 4, "full": 1}  # eta_differences' value -> spp divisor of its sides
# Below this alpha prb's gradient of a dielectric's eta is unreliable, so the optimizer takes
# eta's by central differences (glass blob, 48 px, 16 spp, 5 seeds: at alpha 0.01 its sign was
# wrong 2 times in 5 at eta 1.40, as at the floor; from alpha 0.029 up it matched the
# difference at 1.40 and 1.62, and the difference's two renders would only cost time).
SPECULAR_ALPHA = 0.02


@dataclass(frozen=True)
class Differences:
    """How eta's differences render: their sides at 1/``divisor`` of the job's spp, while
    every width beside the eta shows alpha below ``alpha``."""
    divisor: int
    alpha: float


def differences(value: str) -> Differences:
    """eta_differences' value, SHARE[:ALPHA]: SHARE "on" or "quarter" (sides at a quarter of
    the job's spp) or "full"; ALPHA the width below which they apply (default SPECULAR_ALPHA).
    ValueError saying what it may be."""
    share, colon, alpha = value.partition(":")
    share = "quarter" if share == "on" else share
    try:
        width = float(alpha) if colon else SPECULAR_ALPHA
    except ValueError:
        width = math.nan
    if share not in DIFFERENCE_SPP or not 0 < width <= 1:
        raise ValueError(f"choice 'eta_differences' cannot be '{value}': give on, off, "
                         f"{' or '.join(DIFFERENCE_SPP)}, optionally with :ALPHA (the width "
                         f"below which they apply, in (0, 1]; {SPECULAR_ALPHA:g} unless "
                         "given, e.g. quarter:0.05)")
    return Differences(DIFFERENCE_SPP[share], width)


def settling(name: str) -> Callable[[str], bool]:
    """The value parser of a choice that keeps a rate whole: "on" (a constant-rate choice: the
    full rate to the end; medium_damping: the schedule's) or "settle" (the full rate while its
    variables move steadily, then a shrinking share, or medium_damping's schedule from there):
    True for settle. ValueError saying what it may be."""
    def parse(value: str) -> bool:
        if value not in ("on", "settle"):
            raise ValueError(f"choice '{name}' cannot be '{value}': give on, off or settle")
        return value == "settle"
    return parse


# Choices whose value says more than on/off: name -> its parser (ValueError for a bad one).
CHOICE_OPTIONS = {"multires": coarse_to_fine, "eta_differences": differences,
                  "medium_constant_rate": settling("medium_constant_rate"),
                  "medium_damping": settling("medium_damping"),
                  "roughness_constant_rate": settling("roughness_constant_rate")}


@dataclass(frozen=True)
class SceneInput:
    """A scene bundle by content. ``files`` maps bundle paths to digests and includes
    ``main_file``, the XML Mitsuba loads (already prepared by the daemon: stable ids, float
    textures). ``key`` names this exact content, so a worker can keep what it laid out."""

    key: str
    main_file: str
    files: dict[str, str]
    overrides: dict[str, str]
    display: str  # the user's name for the scene, for messages

    @classmethod
    def of(cls, main_file: str, files: dict[str, str], overrides: dict[str, str],
           display: str) -> SceneInput:
        key = hashlib.sha256(json.dumps([main_file, sorted(files.items()),
                                         sorted(overrides.items())]).encode()).hexdigest()[:32]
        return cls(key, main_file, dict(files), dict(overrides), display)


@dataclass(frozen=True)
class Values:
    """A parameter's values given with a job, flat in Mitsuba's order: inline, or for large
    ones (textures, grids) a .npy blob by digest, which a worker fetches."""

    inline: list[float] = field(default_factory=list)
    sha256: str = ""


@dataclass(frozen=True)
class ReferenceInput:
    """A reference image and what leaves its pixels out of the loss: a mask image of its size
    (weights in [0, 1]) and/or its own alpha channel."""

    sensor: int
    sha256: str  # PNG/JPEG, 8 or 16 bit (sRGB), or OpenEXR (linear)
    name: str    # the user's file name, for messages
    mask_sha256: str = ""  # "": no mask image
    mask_name: str = ""
    alpha_mask: bool = False


@dataclass(frozen=True)
class ParameterSetting:
    """One parameter to optimize. Rate and range default to the scene's listing of it."""

    key: str
    learning_rate: float
    lo: float
    hi: float
    initial: Values | None = None  # None: the scene's value
    smoothness: float = 0.0        # weight of a texture's or grid's smoothness term
    # False: learning_rate is the listing's default, which a choice may replace by its own
    # (large_steps: a share of the mesh's size)
    rate_given: bool = True


@dataclass(frozen=True)
class JobSettings:
    scene: SceneInput
    references: list[ReferenceInput]
    parameters: list[ParameterSetting]
    loss: str = "mse"            # one of engine/losses.LOSSES
    iterations: int = 100
    # Off: a fixed threshold ends dim scenes long before they converge (their loss is small
    # from the start), so a job runs its iterations unless its owner asks for one.
    min_error: float = 0.0
    spp: int = 16                # see engine/parameters.DEFAULT_LEARNING_RATE: one measurement
    seed: int = 0                # iteration i renders with seed + i
    learning_rate: float | None = None  # for parameters given none; None: the scene's default
    schedule: str = "cosine"     # one of SCHEDULES: rates decay along a half cosine to a tenth
    sensor_mode: str = "accumulate"  # one of SENSOR_MODES
    clamp: bool = False
    film_height: int = 0         # 0: the scene's; widths follow each reference's aspect ratio
    truth: dict[str, Values] = field(default_factory=dict)  # known values, for errors
    image_error_every: int = 0   # 0: never
    image_error_spp: int = 64
    fit_exposure: bool = False   # one RGB gain per reference: render * gain ~ reference
    # The most samples (film pixels x spp) one render call may take, the daemon's limit when
    # the job was admitted; 0: no limit. Results render at engine_api.result_spp within it.
    max_samples: int = 0
    # A value per name of CHOICES ("off" turns it off; ALL_CHOICES: every one, a name given
    # as well wins); a choice not named is on.
    choices: dict[str, str] = field(default_factory=dict)
    # lambda of LargeSteps for selected vertex positions (engine/choices/large_steps); 0: chosen
    # from each mesh (the choice, on by default, is turned off as any other: choices)
    large_steps: float = 0.0
    # A sample-count schedule: from iteration N on (key), renders take this spp (value).
    spp_from: dict[int, int] = field(default_factory=dict)
    # Starts compared (engine/starts.py): > 1 runs that many short probes from diverse starts
    # and goes on from the best one; 1: the given start only.
    starts: int = 1

    def spp_at(self, iteration: int) -> int:
        """The spp of iteration i's renders: that of the latest phase begun by i."""
        begun = [n for n in self.spp_from if n <= iteration]
        return self.spp_from[max(begun)] if begun else self.spp

    def choice_on(self, name: str) -> bool:
        return self.choice_value(name) != "off"

    def choice_value(self, name: str) -> str:
        """The value given for the choice (by name, else by ALL_CHOICES), "on" if none (but
        "off" for those OFF_UNLESS_NAMED)."""
        return self.choices.get(name, self.choices.get(
            ALL_CHOICES, "off" if name in OFF_UNLESS_NAMED else "on"))


def read_values(values: Values, read: Callable[[str], bytes], what: str) -> np.ndarray:
    """The components as a flat float32 array, the blob read by digest with ``read``.
    ValueError naming ``what`` when a .npy is not an array of finite numbers."""
    if not values.sha256:
        return np.asarray(values.inline, dtype=np.float32)
    data = read(values.sha256)  # its own errors (a blob not found) as they are
    try:
        array = np.load(io.BytesIO(data), allow_pickle=False)
    except Exception as exc:  # noqa: BLE001 - numpy raises ValueError, OSError, EOFError...
        raise ValueError(f"{what} is not a readable .npy array: "
                         f"{str(exc).strip() or type(exc).__name__}") from None
    if not isinstance(array, np.ndarray) or array.dtype.kind not in "fiub":
        raise ValueError(f"{what} holds {getattr(array, 'dtype', type(array))} data, not "
                         "numbers")
    flat = array.astype(np.float32).ravel()
    if not np.isfinite(flat).all():
        raise ValueError(f"{what} has NaN or infinite components")
    return flat


def npy(values: np.ndarray, shape: list[int]) -> bytes:
    """A .npy of ``values`` in ``shape`` (flat when empty): how large values are kept."""
    buf = io.BytesIO()
    flat = np.asarray(values, dtype=np.float32).ravel()
    np.save(buf, flat.reshape(shape) if shape else flat)
    return buf.getvalue()

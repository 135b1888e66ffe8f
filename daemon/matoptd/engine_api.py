"""The one interface between the daemon and a renderer: what a worker process can be asked.

The daemon's own process (gRPC, store, scheduler) never imports Mitsuba or Dr.Jit. Workers do,
each on its own device, and this module is all the two sides share: plain data in and out
(dataclasses, numbers, strings, bytes, numpy arrays), no protobuf messages, no gRPC errors,
nothing about users or the store. Inputs cross it as content, or as a SHA-256 digest that the
worker resolves with the ``fetch`` function it was given, never as a path into the daemon's
data directory: a worker may run on another machine. A job's inputs are its ``JobSettings``
(``settings.py``), as the daemon admitted them.

A job's run lives on one worker between ``start`` and ``release``: ``step`` runs iterations on
the state it holds (nothing is shipped per iteration), ``checkpoint`` returns everything
needed to continue it elsewhere, bit for bit: ``start(..., checkpoint)`` on any worker goes on
with the same losses it would have had.

    engine.start(job, settings, checkpoint=None) -> Started
    engine.step(job, n)                          -> Progress     (n iterations, records)
    engine.checkpoint(job)                       -> bytes
    engine.result_images(job, sensor)            -> {which: [Image]} (one sensor's renders)
    engine.estimate_part(job, seconds)           -> bool         (standard errors, in turns)
    engine.finish(job, history, cancelled, render) -> Finished   (results, diagnosis)
    engine.estimate(run, settings, checkpoint, which, seconds) -> Estimated | None (in turns)
    engine.release(job)                          -> None         (memory freed)
    engine.describe_scene(scene)                 -> SceneDescription
    engine.render(scene, request)                -> list[Image]
    engine.check_references(references)          -> None
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Protocol

import numpy as np

from .settings import JobSettings, ReferenceInput, SceneInput
from .truth import ParameterError

Fetch = Callable[[str], bytes]  # sha256 -> the blob's bytes (raises KeyError when unknown)

# Parameter kinds, as the API names them (lower case of ParameterKind).
KINDS = ("scalar", "rgb", "texture", "volume_grid", "vertex_array", "transform", "vector")

# -- errors ---------------------------------------------------------------------------------

class EngineError(Exception):
    """A request the engine could not carry out; the message is for the user as it stands."""


class InvalidInput(EngineError):
    """The caller's input is at fault: an XML Mitsuba rejects, an unreadable image, a
    parameter value of the wrong size. The daemon answers INVALID_ARGUMENT."""


class OutOfMemory(EngineError):
    """The device or the worker ran out of memory for this request."""


# -- scenes ---------------------------------------------------------------------------------

@dataclass
class SensorInfo:
    index: int
    id: str
    width: int
    height: int


@dataclass
class ParameterInfo:
    """A differentiable parameter: its kind (one of KINDS), shape, current value (when it has at
    most ``SMALL`` components), legal range and default learning rate."""

    key: str
    kind: str
    shape: list[int]
    value: list[float]
    lo: float
    hi: float
    learning_rate: float
    discontinuous: bool


SMALL = 64  # parameters up to this many components travel inline in records and listings


@dataclass
class SceneDescription:
    sensors: list[SensorInfo]
    has_media: bool
    parameters: list[ParameterInfo]


@dataclass
class RenderRequest:
    """A preview or synthetic reference: the scene's own integrator, ``values`` instead of the
    scene's for the keys given (flat, Mitsuba's order), restored afterwards."""

    values: dict[str, np.ndarray]
    spp: int = 64  # RenderScene's default: a preview to look at
    sensors: list[int] = field(default_factory=list)  # empty: all
    seed: int = 0


@dataclass
class Image:
    """A rendered or decoded image: linear OpenEXR and 8-bit sRGB PNG bytes. ``role`` is
    "render", "initial", "optimized", "reference", "error" or "texture" (then ``parameter``
    names the texture)."""

    sensor: int
    role: str
    width: int
    height: int
    exr: bytes
    png: bytes
    parameter: str = ""


# -- jobs -----------------------------------------------------------------------------------

RESULT_SPP = 64  # results are renders to look at, off the clock


def reference_film(height: int, reference_width: int, reference_height: int
                   ) -> tuple[int, int]:
    """The film (width, height) a sensor renders at for a reference: the given height, the
    width its aspect ratio asks for. Daemon and engine both size films by this rule: the
    daemon to estimate a job's cost before a worker sees it, the engine to render."""
    return max(1, round(height * reference_width / reference_height)), height


def result_spp(spp: int, pixels: int, max_samples: int) -> int:
    """Samples per pixel of a result render: RESULT_SPP (or the job's own spp, if more), but
    never more samples in one call than ``max_samples`` allows, nor fewer than the job's
    iterations used, which the daemon admitted."""
    wanted = max(RESULT_SPP, spp)
    if max_samples <= 0:
        return wanted
    return max(spp, min(wanted, max_samples // max(1, pixels)))


@dataclass
class ChoiceStatus:
    """A choice that concerns the job: on (in force) or turned off by its settings, why in
    words, and what it cost: its hooks' seconds per iteration so far, and once at the start."""

    name: str
    on: bool
    why: str
    seconds_per_iteration: float = 0.0
    setup_seconds: float = 0.0
    switchable: bool = True  # False: a setting asks for it (fit_exposure, a smoothness weight)


@dataclass
class Started:
    """A job's run, loaded. ``iteration`` is where it goes on (0, or the checkpoint's)."""

    iteration: int
    integrator: str
    integrator_reason: str
    sensors: list[int]           # the sensors it renders (those with a reference)
    notes: list[str]
    shapes: dict[str, list[int]]  # of every optimized parameter
    kinds: dict[str, str]
    choices: list[ChoiceStatus] = field(default_factory=list)
    # A fresh job that compared starts (JobSettings.starts): the iterations its best probe ran,
    # which are the job's first ones. None otherwise.
    probed: Progress | None = None


@dataclass
class IterationRecord:
    """Iteration i: the loss of the parameters theta_i, and theta_i itself (parameters with at
    most SMALL components). ``seconds``: optimizing time since the job began."""

    iteration: int
    seconds: float
    loss: float
    values: dict[str, np.ndarray]
    errors: dict[str, ParameterError] = field(default_factory=dict)  # with ground truth
    image_error: float | None = None
    gains: dict[int, np.ndarray] = field(default_factory=dict)  # sensor -> RGB (fit_exposure)
    spp: int = 0  # what its renders took (0: kept before it was recorded)


@dataclass
class Counters:
    """How often the numerical guards acted, so far."""

    nonfinite_gradient_steps: int = 0  # steps with NaN/Inf gradient components (zeroed)
    skipped_steps: int = 0             # steps skipped because the loss was NaN/Inf
    clamped_components: int = 0        # components held at their range after a step


@dataclass
class Progress:
    records: list[IterationRecord]
    done: bool               # ran all iterations or reached min_error
    stop_reason: str         # "iterations" or "min_error" once done
    best_iteration: int      # -1 before there is one
    best_loss: float
    seconds: float           # optimizing time so far
    counters: Counters
    choices: list[ChoiceStatus] = field(default_factory=list)


# How a component's verdict reads (engine/verdicts.py): value +- error; at a bound (or the
# floor a value is shown at) the interval is one-sided, away from it; not determined: the
# images do not decide it (the error is +inf, and a reason says why).
READINGS = ("two_sided", "at_lower_bound", "at_upper_bound", "not_determined")


@dataclass
class StandardError:
    """A value's verdict: one standard error per component (same order), how to read each
    (one of READINGS) and, for a component not determined, why in a few words ("" for the
    others; an empty list when none has a reason)."""

    error: np.ndarray
    reading: list[str]
    reason: list[str] = field(default_factory=list)


@dataclass
class Result:
    """The parameters of one iteration (``which``: "best" or "last") with the renders they give,
    and the optimized scene as files next to the original main XML."""

    which: str
    iteration: int
    loss: float
    values: dict[str, np.ndarray]           # flat
    initial_values: dict[str, np.ndarray]
    images: list[Image]
    scene_files: dict[str, bytes]           # new files, paths relative to the main XML's folder
    scene_file: str                         # the optimized XML among them
    unplaced: list[str]                     # keys the XML could not be made to hold
    gains: dict[int, np.ndarray] = field(default_factory=dict)  # sensor -> RGB (fit_exposure)
    # Of the parameters up to a few dozen components in all (textures and grids: a note), and
    # of the gains: how far each value may be from the truth.
    standard_errors: dict[str, StandardError] = field(default_factory=dict)
    gain_errors: dict[int, StandardError] = field(default_factory=dict)


@dataclass
class Estimated:
    """Standard errors of one kept iteration of a paused job, estimated on request."""

    errors: dict[str, StandardError]
    gain_errors: dict[int, StandardError]
    notes: list[str]  # pairs that trade off, what is not determined, the estimate's cost


@dataclass
class Finished:
    results: list[Result]
    notes: list[str]  # the diagnosis: what went wrong when the job did not converge
    counters: Counters


# -- the interface --------------------------------------------------------------------------

class Engine(Protocol):
    """What a worker does. One call at a time; a job's calls go to the worker that started it."""

    def describe_scene(self, scene: SceneInput) -> SceneDescription:
        """Loads the scene and lists its sensors and differentiable parameters."""

    def render(self, scene: SceneInput, request: RenderRequest) -> list[Image]:
        """Renders with the scene's own integrator (a preview or a synthetic reference)."""

    def check_references(self, references: list[ReferenceInput]) -> None:
        """Raises InvalidInput naming the first reference (or mask) that is not a readable
        image, whose mask does not fit it, or that leaves no pixel to compare."""

    def start(self, job: str, settings: JobSettings, checkpoint: bytes | None) -> Started:
        """Loads a job's run (from a checkpoint when given) and holds it until ``release``."""

    def step(self, job: str, n: int) -> Progress:
        """Runs up to ``n`` iterations (fewer when the job is done)."""

    def checkpoint(self, job: str) -> bytes:
        """Everything needed to continue exactly: values, Adam's state, best, clock."""

    def result_images(self, job: str, sensor: int) -> dict[str, list[Image]]:
        """One sensor's result images per result ("best", "last"): initial, optimized,
        reference, error. The end phase makes them one sensor per call."""

    def estimate_part(self, job: str, seconds: float) -> bool:
        """The standard errors of the job's end for about ``seconds``; True once done. The
        end phase asks until they are, one turn of the worker each; ``finish`` then uses
        them (without these calls, it estimates them itself)."""

    def finish(self, job: str, history: list[IterationRecord], cancelled: bool,
               render: bool = True) -> Finished:
        """The job's results (best, and last unless it was cancelled before a step returned)
        and its diagnosis, from its history as the daemon recorded it. Without ``render``,
        no per-sensor images (``result_images`` made them)."""

    def estimate(self, run: str, settings: JobSettings | None, checkpoint: bytes | None,
                 which: str, seconds: float) -> Estimated | None:
        """Standard errors of a paused job's kept iteration ("best" or "last"), from its
        checkpoint, for about ``seconds`` a call: None until they are done. The daemon asks
        until they are, one turn of the worker each (the same worker: it holds the ``run``,
        loaded by the first call, released by the last). Later calls may leave out the
        settings and checkpoint; one that finds the run gone then raises EngineError, and
        with them loads it again."""

    def release(self, job: str) -> None:
        """Forgets the job's run and returns its memory."""


# The calls a worker answers, by name: a worker dispatches these and no other attribute.
METHODS = frozenset(name for name in vars(Engine) if not name.startswith("_"))

"""The daemon's records: a job, a scene, a result and the images and files they name, as the
store keeps them (JSON) and the server shows them (``server/convert.py`` builds the API's
messages from them, and only there).

A job's whole state is one ``JobRecord`` with one ``Phase``. The scheduler owns the phase:
every change of it is a transition of ``scheduling/scheduler.py``; the lanes fill in what the
engine reports (progress, the run's facts, results) and the store persists the record as it
stands after each change.
"""

from __future__ import annotations

import copy
import enum
from dataclasses import dataclass, field, replace

from .engine_api import ChoiceStatus, Counters, SensorInfo, StandardError
from .settings import JobSettings, SceneInput, Values


class Phase(enum.Enum):
    """Where a job is in its life. The API shows fewer states (``state``): pausing,
    cancelling and ending read as RUNNING there, with a note for the end phase."""

    QUEUED = "queued"          # waits for a worker: its first load, or a reload elsewhere
    RUNNING = "running"        # has been loaded; iterates in slices, between them it waits
    PAUSING = "pausing"        # pause asked while loaded: it parks at its next boundary
    PAUSED = "paused"          # parked (checkpointed, released); resume continues it
    CANCELLING = "cancelling"  # cancel asked: its iterations stop at the next boundary
    ENDING = "ending"          # iterations over: result images, one sensor per turn, then end
    SUCCEEDED = "succeeded"
    FAILED = "failed"
    CANCELLED = "cancelled"
    INTERRUPTED = "interrupted"  # the daemon stopped while it ran; resume continues it

    @property
    def state(self) -> str:
        """The state the API shows, by its short name."""
        return SHOWN.get(self, self.name)

    @property
    def final(self) -> bool:
        return self in FINAL

    @property
    def active(self) -> bool:
        """Wants a worker now or soon: counts against its owner's jobs."""
        return self in ACTIVE


SHOWN = {Phase.PAUSING: "RUNNING", Phase.CANCELLING: "RUNNING", Phase.ENDING: "RUNNING"}
FINAL = frozenset({Phase.SUCCEEDED, Phase.FAILED, Phase.CANCELLED})
ACTIVE = frozenset({Phase.QUEUED, Phase.RUNNING, Phase.PAUSING, Phase.CANCELLING,
                    Phase.ENDING})
RESUME_PENDING = "pending"  # resumed_from until the next load says from where


@dataclass
class ImageRef:
    """A rendered image kept as two blobs: linear OpenEXR and 8-bit sRGB PNG. ``role`` as in
    ``engine_api.Image``."""

    sensor: int
    role: str
    width: int
    height: int
    exr: str  # sha256
    png: str
    parameter: str = ""


@dataclass
class BundleFile:
    path: str
    sha256: str


@dataclass
class Ending:
    """A job's end phase: its iterations are over, and it renders its result images one
    sensor per turn of its worker (``parts`` of them), estimates its standard errors over as
    many turns as they take, then finishes as ``outcome``."""

    outcome: Phase  # SUCCEEDED or CANCELLED
    reason: str     # "iterations", "min_error" or "cancelled"
    parts: int
    done: int = 0
    estimated: bool = False  # the standard errors; a worker lost meanwhile estimates anew
    images: dict[str, list[ImageRef]] = field(default_factory=dict)  # made, per "best"/"last"

    @property
    def next(self) -> str:
        """What the end phase does next: "results", "estimate" or "finish" (no estimate
        without a result: ``parts`` 0)."""
        if self.done < self.parts:
            return "results"
        return "estimate" if self.parts and not self.estimated else "finish"


@dataclass
class JobRecord:
    name: str
    owner: str
    scene: str               # "scenes/..." it was created on
    settings: JobSettings    # as admitted; never changes
    phase: Phase = Phase.QUEUED
    created: float = 0.0     # seconds since the epoch
    updated: float = 0.0
    iteration: int = 0       # iterations completed
    loss: float = 0.0        # of the last one
    best_iteration: int = -1
    best_loss: float = 0.0
    elapsed: float = 0.0     # optimizing time, seconds
    counters: Counters = field(default_factory=Counters)
    # What its last load said: the integrator (and why), the sensors it renders, the shape
    # of each optimized parameter, the worker.
    integrator: str = ""
    integrator_reason: str = ""
    sensors: list[int] = field(default_factory=list)
    shapes: dict[str, list[int]] = field(default_factory=dict)
    worker: str = ""
    choices: list[ChoiceStatus] = field(default_factory=list)  # as the engine last reported
    # Once it has ended with a result: its best result's small values, with their errors.
    best_values: dict[str, Values] = field(default_factory=dict)
    best_errors: dict[str, StandardError] = field(default_factory=dict)
    resumed_from: str = ""
    checkpoint: int | None = None  # the iteration its latest checkpoint continues from
    ending: Ending | None = None
    error: str = ""          # why it FAILED
    stop_reason: str = ""    # "iterations", "min_error", "cancelled", "failed", or why it stopped
    notes: list[str] = field(default_factory=list)

    def snapshot(self) -> JobRecord:
        """A copy that later changes to this record leave alone (the settings are shared:
        they never change)."""
        return replace(self, counters=replace(self.counters), sensors=list(self.sensors),
                       shapes=dict(self.shapes), notes=list(self.notes),
                       choices=list(self.choices),
                       ending=copy.deepcopy(self.ending))


@dataclass
class SceneRecord:
    name: str
    owner: str
    display_name: str
    main_file: str           # the bundle path of the XML the user named
    files: list[BundleFile]  # the bundle as uploaded
    overrides: dict[str, str]
    warnings: list[str]
    sensors: list[SensorInfo]
    has_media: bool
    parameter_count: int
    # What a worker loads (the prepared XML among the files); None for scenes made before
    # the daemon kept it, which cannot be loaded again.
    inputs: SceneInput | None
    created: float = 0.0


@dataclass
class ResultRecord:
    """One result of a job ("best" or "last"): parameter values with the renders they give,
    and the optimized scene as a bundle (the original files and the new ones)."""

    job: str
    which: str
    iteration: int
    loss: float
    values: dict[str, Values]
    initial: dict[str, Values]
    shapes: dict[str, list[int]]
    images: list[ImageRef]
    scene_files: list[BundleFile]
    scene_file: str          # the optimized XML's bundle path
    unplaced: list[str]      # keys the XML could not be made to hold
    gains: dict[int, list[float]] = field(default_factory=dict)  # sensor -> RGB
    # How far each small value and gain may be from the truth (engine/uncertainty.py).
    standard_errors: dict[str, StandardError] = field(default_factory=dict)
    gain_errors: dict[int, StandardError] = field(default_factory=dict)

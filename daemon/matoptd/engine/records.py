"""The loop's state as plain data: one record per variable Adam steps, as Dr.Jit's ``opt.py``
keeps one per parameter (``state[key] = (value, promoted, lr, extra)``), and the iterations
the loop keeps.

A variable is a selected scene parameter or a choice's own (an exposure gain). Adam's moments
stay in ``mi.ad.Adam`` under the record's key; everything else the loop, the choices, the
checkpoint and the standard errors know of a variable is here, declared once. ``CHECKPOINTED``
names the fields a checkpoint carries (engine/checkpoint.py writes them by name).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..truth import ParameterError
from .starts import Probe

GAIN = "gain"  # the kind of an exposure gain's record (the others are the API's KINDS)


@dataclass(eq=False)
class ParamRecord:
    """One variable u that Adam steps, and the value v = decode(expand(u)) the scene renders.

    lo, hi      the range v is kept in, as the job gives it
    bounds      the range u is clipped to after a step (the choices' maps of lo, hi)
    rate        the base rate as given (``rate_given``) or listed; ``step_rate`` what this
                step uses before the schedule's share (a choice may scale it:
                linear_extinction, large_steps)
    start       v_0, flat, in range (a choice may replace it: black_start)
    scene       the scene's own value (None for a gain)
    current     theta_i's v once the loop has read it
    held        iterations whose step a choice held (no step taken; its gradient not the
                images')
    schedule_begin  the step the rate schedule's decay starts from (0: the job's first; a
                choice that releases a variable mid-job restarts it there: eta_hold)
    decays      whether the schedule's decay applies to its rate (a choice may keep it whole:
                medium_constant_rate)
    gradients   the latent gradient of each recent step (small variables only; NaN: held)
    means       v's mean per iteration (variables too large for the iteration records)
    """

    key: str
    kind: str
    lo: float
    hi: float
    rate: float
    start: np.ndarray
    scene: np.ndarray | None = None
    initial_given: bool = False   # the job gave v_0 (``--init``, a restart)
    rate_given: bool = True       # False: the listing's default rate
    smoothness: float = 0.0       # the job's smoothness weight (textures and grids)
    channels: int = 0             # a texture's or grid's channel count; 0 otherwise
    shape: tuple[int, ...] = ()   # the scene value's shape (a tensor's), () for a vector
    sensor: int = -1              # a gain's sensor
    truth: np.ndarray | None = None
    bounds: tuple[float, float] = (-math.inf, math.inf)
    step_rate: float = 0.0
    current: np.ndarray | None = None
    held: list[int] = field(default_factory=list)
    schedule_begin: int = 0
    decays: bool = True
    gradients: list[np.ndarray] = field(default_factory=list)
    means: list[float] = field(default_factory=list)

    @property
    def size(self) -> int:
        return int(self.start.size)

    @property
    def is_gain(self) -> bool:
        return self.kind == GAIN


# What a checkpoint keeps of each record (the rest follows from the job's settings).
CHECKPOINTED = ("held",)


@dataclass
class Best:
    """An iteration and the parameters that produced its loss (the best so far, or the last)."""

    iteration: int = -1
    loss: float = math.inf
    values: dict[str, np.ndarray] = field(default_factory=dict)
    gains: dict[int, np.ndarray] = field(default_factory=dict)


@dataclass
class Progress:
    """The loop's own counters and kept iterations: what a checkpoint restores besides the
    records, Adam and the choices."""

    iteration: int = 0            # the next iteration to run
    elapsed: float = 0.0          # optimizing seconds, excluding pauses and other jobs' turns
    nonfinite_steps: int = 0      # steps with a NaN/Inf gradient component (zeroed)
    skipped_steps: int = 0        # steps skipped because the loss was NaN/Inf
    clamped: int = 0              # components a step pushed out of their bounds
    recent: list[float] = field(default_factory=list)  # the last ``window`` finite losses
    best: Best = field(default_factory=Best)
    last: Best = field(default_factory=Best)  # the latest iteration run
    probes: list[Probe] = field(default_factory=list)  # the starts compared (JobSettings.starts)


@dataclass
class Step:
    """What iteration i did: its loss, theta_i, whether the job is done and why."""

    iteration: int
    loss: float
    values: dict[str, np.ndarray]  # theta_i (all selected parameters)
    done: bool
    stop_reason: str = ""
    errors: dict[str, ParameterError] = field(default_factory=dict)
    image_error: float | None = None
    gains: dict[int, np.ndarray] = field(default_factory=dict)  # sensor -> RGB gain
    spp: int = 0                   # what its renders took

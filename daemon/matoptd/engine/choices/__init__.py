"""The engine's named choices: each special case of the optimization loop (optimize.py) as an
object that declares its state and its hooks (base.py), in the order the loop calls them.

The order matters where hooks meet, and the choices that meet declare it (``after``,
``yields_to``), which ``check_declarations`` holds against this order at import: a colour's
start is changed (black_start) before it is encoded; a texture's coarse level is blown up
(multires, ``expand``) before its value is decoded, exp(u) (log_space) before the principled
roughness's floor (roughness_floor); gains multiply the renders (exposure_gains) before eta's
differences read them; eta's hold marks it held before its differences would be rendered for
nothing. Both leave the keys that gauss_newton steps, while it is on. log_space leaves a
homogeneous sigma_t to linear_extinction while that is on, and slow_interface_width takes a
share of the relative rate log_space gives a width. frozen comes last: it begins once the
others have said what they do to the renders.
"""

from __future__ import annotations

from ...settings import CHOICES, JobSettings
from .base import (HOLD, Begun, Choice, ConflictError, State, assign_keys,
                   check_declarations, overrides)
from .black_start import BlackStart
from .depth import Depth
from .eta_differences import EtaDifferences
from .eta_hold import EtaHold
from .exposure_gains import ExposureGains
from .filter_scaling import FilterScaling, Loading
from .frozen import Frozen
from .gauss_newton import GaussNewton
from .large_steps import LargeSteps
from .linear_extinction import LinearExtinction
from .log_space import LogSpace
from .medium_constant_rate import MediumConstantRate
from .medium_damping import MediumDamping
from .multires import Multires
from .roughness_constant_rate import RoughnessConstantRate
from .roughness_floor import RoughnessFloor
from .slow_interface_width import SlowInterfaceWidth
from .smoothness import Smoothness

REGISTRY: tuple[type[Choice], ...] = (
    FilterScaling, Depth, BlackStart, Multires, LargeSteps, LogSpace, LinearExtinction,
    SlowInterfaceWidth, MediumConstantRate, MediumDamping, RoughnessConstantRate,
    RoughnessFloor, ExposureGains, Smoothness, EtaHold, EtaDifferences, GaussNewton, Frozen)

# The API names every switchable choice (settings.CHOICES): the two lists are one fact.
assert {c.name for c in REGISTRY if c.switchable} == set(CHOICES), "settings.CHOICES"
check_declarations(REGISTRY)


def build(settings: JobSettings) -> list[Choice]:
    """A job's choices, each on unless its settings turn it off."""
    return [c(settings) for c in REGISTRY]


__all__ = ["HOLD", "Begun", "Choice", "ConflictError", "State", "Loading", "REGISTRY",
           "assign_keys", "build", "overrides"]

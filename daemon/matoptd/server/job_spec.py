"""A JobSpec becomes a job's ``JobSettings``: checked in the caller's terms against its scene,
every value it gives decoded once (a malformed .npy is refused here, not when the job loads),
and what it leaves out set to the defaults of ``settings.py`` and of the scene's parameter
listing. The settings are then used as they are by the store, the scheduler and the engine."""

from __future__ import annotations

import difflib
import math
from dataclasses import dataclass, field

from matopt_api import enums
from matopt_api.v1 import matopt_pb2 as pb

from .. import range_notes
from ..engine_api import ParameterInfo
from ..errors import FailedPrecondition, InvalidArgument
from ..records import ResultRecord, SceneRecord
from ..settings import (ALL_CHOICES, CHOICE_OPTIONS, CHOICE_VALUES, CHOICES, MAX_STARTS,
                        JobSettings, ParameterSetting, ReferenceInput, SceneInput, Values,
                        read_values)
from .convert import given_values

PARAMETER_KINDS_SMOOTHED = ("texture", "volume_grid")


@dataclass
class StartFrom:
    """A restart: parameters without a start value of their own take ``result``'s."""

    job: str     # "jobs/..."
    which: str   # "best" or "last"
    result: ResultRecord


@dataclass
class Built:
    settings: JobSettings
    notes: list[str] = field(default_factory=list)  # start values clipped into their range


def given_blobs(spec: pb.JobSpec) -> set[str]:
    """The blobs a spec names (references, masks, start values, ground truth): checked first,
    so that another user's blob fails exactly as a missing one."""
    return {b.removeprefix("blobs/") for b in (
        *(r.blob for r in spec.references), *(r.mask_blob for r in spec.references),
        *(p.initial_blob for p in spec.parameters), *(t.blob for t in spec.ground_truth)) if b}


def build(spec: pb.JobSpec, scene: SceneRecord, params: dict[str, ParameterInfo], read,
          start: StartFrom | None = None, max_samples: int = 0) -> Built:
    """``read``: digest -> bytes of the caller's blobs (references and .npy values must be
    theirs); ``max_samples``: the daemon's limit on one render call."""
    inputs = loadable(scene)
    given = _settings(spec)
    references = _references(spec, scene)
    notes: list[str] = []
    parameters = [_parameter(p, spec, scene, params, read, start, notes)
                  for p in _selected(spec, scene, params)]
    truth = {}
    for t in spec.ground_truth:
        if t.key not in params:
            raise InvalidArgument(f"ground truth for unknown parameter key '{t.key}'")
        what = f"ground truth of '{t.key}'"
        if not t.blob and len(t.value) != _size(params[t.key]):
            raise InvalidArgument(f"{what} has {len(t.value)} component(s), expected "
                                  f"{_size(params[t.key])}")
        values = given_values(t.value, t.blob) or Values()
        _decoded(values, t.blob, what, params[t.key], read)
        truth[t.key] = values
    return Built(JobSettings(scene=inputs, references=references, parameters=parameters,
                             truth=truth, max_samples=max_samples, **given), notes)


def _settings(spec: pb.JobSpec) -> dict:
    """The job-wide settings the spec gives; the others keep their defaults."""
    if spec.HasField("iterations") and spec.iterations < 1:
        raise InvalidArgument(f"iterations must be >= 1, got {spec.iterations}")
    if spec.HasField("spp") and spec.spp < 1:
        raise InvalidArgument(f"spp must be >= 1, got {spec.spp}")
    if spec.HasField("min_error") and not math.isfinite(spec.min_error):
        raise InvalidArgument(f"min_error must be finite, got {spec.min_error}")
    for name in ("film_height", "image_error_every", "image_error_spp"):
        if getattr(spec, name) < 0:
            raise InvalidArgument(f"{name} must be >= 0, got {getattr(spec, name)}")
    if spec.HasField("learning_rate") and not (math.isfinite(spec.learning_rate)
                                               and spec.learning_rate > 0):
        raise InvalidArgument(f"learning_rate must be > 0, got {spec.learning_rate}")
    if spec.HasField("starts") and not 1 <= spec.starts <= MAX_STARTS:
        raise InvalidArgument(f"starts must be 1 to {MAX_STARTS}, got {spec.starts}")
    given = {name: getattr(spec, name) for name in ("iterations", "min_error", "spp",
                                                    "learning_rate", "starts")
             if spec.HasField(name)}
    for name, enum in (("loss", pb.Loss), ("schedule", pb.Schedule),
                       ("sensor_mode", pb.SensorMode)):
        if getattr(spec, name):  # UNSPECIFIED: the default
            given[name] = enums.short_name(enum, getattr(spec, name)).lower()
    # 0 in these means "the default" (or "off", which is their default)
    given.update({name: getattr(spec, name) for name in
                  ("seed", "clamp", "film_height", "image_error_every", "image_error_spp",
                   "fit_exposure") if getattr(spec, name)})
    if spec.choices:
        given["choices"] = _choices(spec.choices)
    if spec.large_steps_lambda:
        if not (math.isfinite(spec.large_steps_lambda) and spec.large_steps_lambda > 0):
            raise InvalidArgument(f"large_steps_lambda must be > 0, got "
                                  f"{spec.large_steps_lambda}")
        if not any(p.key.endswith(".vertex_positions") for p in spec.parameters):
            raise InvalidArgument("large_steps_lambda steps vertex positions, and the job "
                                  "selects none")
        if spec.choices.get("large_steps") == "off":
            raise InvalidArgument("large_steps_lambda asks for large steps, and the choice "
                                  "large_steps=off turns them off: drop one of the two")
        given["large_steps"] = spec.large_steps_lambda
    if spec.spp_from:
        given["spp_from"] = _spp_from(spec.spp_from, given.get("iterations",
                                                              JobSettings.iterations))
    return given


def _spp_from(phases, iterations: int) -> dict[int, int]:
    """JobSpec.spp_from: phases that begin within the job, at 1 spp or more."""
    for first, spp in sorted(phases.items()):
        if not 1 <= first < iterations:
            raise InvalidArgument(f"spp_from {first}:{spp} begins at iteration {first}, "
                                  f"outside the job's 1 to {iterations - 1}")
        if spp < 1:
            raise InvalidArgument(f"spp_from {first}:{spp} must take >= 1 spp")
    return dict(sorted(phases.items()))


def _choices(choices) -> dict[str, str]:
    """JobSpec.choices: names the engine has (or "all"), values it accepts."""
    names = [*CHOICES, ALL_CHOICES]
    for name, value in choices.items():
        if name not in names:
            close = difflib.get_close_matches(name, names, n=1)
            raise InvalidArgument(f"unknown choice '{name}'"
                                  + (f" (did you mean '{close[0]}'?)" if close else "")
                                  + f"; the choices are {', '.join(names)}")
        if name in CHOICE_OPTIONS and value != "off":
            try:
                CHOICE_OPTIONS[name](value)
            except ValueError as exc:
                raise InvalidArgument(str(exc)) from None
        elif value not in CHOICE_VALUES:
            raise InvalidArgument(f"choice '{name}' cannot be '{value}': give "
                                  f"{' or '.join(CHOICE_VALUES)}")
    return dict(choices)


def _references(spec: pb.JobSpec, scene: SceneRecord) -> list[ReferenceInput]:
    count = len(scene.sensors)
    refs = list(spec.references)
    if spec.fit_exposure and not refs:
        raise InvalidArgument("fit_exposure fits one gain per reference image, but the job "
                              "has no reference images")
    if not refs:
        raise InvalidArgument(f"no reference images: the scene has {count} sensor(s)")
    explicit = [r.HasField("sensor") for r in refs]
    if any(explicit) and not all(explicit):
        raise InvalidArgument("either every reference names its sensor or none does")
    if not any(explicit) and len(refs) != count:
        raise InvalidArgument(f"got {len(refs)} reference image(s) for a scene with {count} "
                              f"sensor(s): give one per sensor, in order, or name the sensor "
                              f"of each")
    out, seen = [], set()
    for i, r in enumerate(refs):
        label = r.filename or r.blob
        index = r.sensor if r.HasField("sensor") else i
        if not 0 <= index < count:
            raise InvalidArgument(f"reference '{label}' names sensor {index}, but the scene "
                                  f"has {count} sensor(s)")
        if index in seen:
            raise InvalidArgument(f"two reference images for sensor {index}")
        seen.add(index)
        if r.mask_filename and not r.mask_blob:
            raise InvalidArgument(f"reference '{label}' names mask file '{r.mask_filename}' "
                                  "but no mask_blob: upload the mask and give its blob")
        out.append(ReferenceInput(index, r.blob.removeprefix("blobs/"), label,
                                  r.mask_blob.removeprefix("blobs/"),
                                  r.mask_filename or r.mask_blob, r.alpha_mask))
    return out


def _selected(spec: pb.JobSpec, scene: SceneRecord, params: dict[str, ParameterInfo]
              ) -> list[pb.ParameterSpec]:
    if not spec.parameters:
        raise InvalidArgument("no parameters selected: name at least one key "
                              "(ListSceneParameters shows them)")
    keys = set()
    for p in spec.parameters:
        listed(p.key, params, scene)
        if p.key in keys:
            raise InvalidArgument(f"parameter '{p.key}' is selected twice")
        keys.add(p.key)
    return list(spec.parameters)


def _parameter(p: pb.ParameterSpec, spec: pb.JobSpec, scene: SceneRecord,
               params: dict[str, ParameterInfo], read, start: StartFrom | None,
               notes: list[str]) -> ParameterSetting:
    info = params[p.key]
    lr = p.learning_rate if p.HasField("learning_rate") else (
        spec.learning_rate if spec.HasField("learning_rate") else info.learning_rate)
    if not (math.isfinite(lr) and lr > 0):
        raise InvalidArgument(f"learning rate of '{p.key}' must be > 0, got {lr}")
    lo = p.min if p.HasField("min") else info.lo
    hi = p.max if p.HasField("max") else info.hi
    if not lo < hi:
        raise InvalidArgument(f"range of '{p.key}' is empty: min {lo} >= max {hi}")
    if lo < info.lo or hi > info.hi:
        raise InvalidArgument(f"range [{lo}, {hi}] of '{p.key}' leaves its legal range "
                              f"[{info.lo}, {info.hi}]")
    what = f"initial value of '{p.key}'"
    if p.initial_value and len(p.initial_value) != _size(info):
        raise InvalidArgument(f"{what} has {len(p.initial_value)} component(s), expected "
                              f"{_size(info)}")
    if any(not math.isfinite(v) for v in p.initial_value):
        raise InvalidArgument(f"{what} is not finite")
    if not (math.isfinite(p.smoothness) and p.smoothness >= 0):
        raise InvalidArgument(f"smoothness of '{p.key}' must be >= 0, got {p.smoothness}")
    if p.smoothness and info.kind not in PARAMETER_KINDS_SMOOTHED:
        raise InvalidArgument(f"smoothness applies to textures and grids; '{p.key}' is of "
                              f"kind {info.kind}")
    initial, source = given_values(p.initial_value, p.initial_blob), "the initial value"
    if initial is None and start is not None and p.key in start.result.values:
        initial = start.result.values[p.key]
        source = f"the {start.which} result of {start.job}"
    if initial is not None:
        value = _decoded(initial, p.initial_blob, what, info, read)
        note = range_notes.clip_note(p.key, value, lo, hi, source)
        if note:
            notes.append(note)
    return ParameterSetting(p.key, lr, lo, hi, initial, p.smoothness,
                            p.HasField("learning_rate") or spec.HasField("learning_rate"))


def _decoded(values: Values, blob: str, what: str, info: ParameterInfo, read):
    """The values as an array; a .npy blob must hold as many components as the parameter."""
    try:
        array = read_values(values, read, what)
    except ValueError as exc:
        raise InvalidArgument(str(exc)) from None
    if blob and array.size != _size(info):
        raise InvalidArgument(f"{what} ({blob}) has {array.size} component(s), expected "
                              f"{_size(info)} (shape {list(info.shape)})")
    return array


def _size(info: ParameterInfo) -> int:
    return math.prod(info.shape) if info.shape else 1


def loadable(scene: SceneRecord) -> SceneInput:
    """What a worker loads of the scene; scenes made before the daemon kept it cannot be."""
    if scene.inputs is None:
        raise FailedPrecondition(f"scene '{scene.name}' was made by an older matoptd; create "
                                 "it again")
    return scene.inputs


def listed(key: str, params: dict[str, ParameterInfo], scene: SceneRecord) -> ParameterInfo:
    """The scene's parameter ``key``, or INVALID_ARGUMENT with the closest listed key."""
    if key not in params:
        close = difflib.get_close_matches(key, list(params), n=1)
        hint = f"; did you mean '{close[0]}'?" if close else ""
        raise InvalidArgument(f"unknown parameter key '{key}' in scene '{scene.display_name}' "
                              f"(ListSceneParameters lists the parameters that can be set: the "
                              f"differentiable ones){hint}")
    return params[key]


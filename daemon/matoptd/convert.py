"""Between the API's protobuf messages and the engine's plain data (``engine_api``): the only
place the two meet. Large parameter values travel in the API as ``.npy`` blobs; here they are
decoded (and refused with a message naming the key when they are not what they claim) or
encoded, so the engine only ever sees arrays.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
from typing import Callable

import numpy as np

from matopt_api import enums
from matopt_api.v1 import matopt_pb2 as pb

from . import engine_api as api
from .errors import InvalidArgument

PutBlob = Callable[[bytes], str]     # bytes -> "blobs/{sha256}"
ReadBlob = Callable[[str], bytes]    # "blobs/{sha256}" -> bytes


# -- values -----------------------------------------------------------------------------------

def npy(data: bytes, what: str) -> np.ndarray:
    """A flat float32 array from ``.npy`` bytes; INVALID_ARGUMENT naming ``what`` otherwise."""
    try:
        array = np.load(io.BytesIO(data), allow_pickle=False)
    except Exception as exc:  # noqa: BLE001 - numpy raises ValueError, OSError, EOFError...
        raise InvalidArgument(f"{what} is not a readable .npy array: "
                              f"{str(exc).strip() or type(exc).__name__}") from None
    if not isinstance(array, np.ndarray) or array.dtype.kind not in "fiub":
        raise InvalidArgument(f"{what} holds {getattr(array, 'dtype', type(array))} data, "
                              "not numbers")
    flat = array.astype(np.float32).ravel()
    if not np.isfinite(flat).all():
        raise InvalidArgument(f"{what} has NaN or infinite components")
    return flat


def value(v: pb.ParameterValue | pb.ParameterSpec, read_blob: ReadBlob, blob: str,
          inline, what: str) -> np.ndarray | None:
    if blob:
        return npy(read_blob(blob), what)
    return np.asarray(inline, dtype=np.float32) if len(inline) else None


def values_to_pb(values: dict[str, np.ndarray], shapes: dict[str, list[int]],
                 put_blob: PutBlob | None,
                 errors: dict[str, api.StandardError] | None = None
                 ) -> list[pb.ParameterValue]:
    """Small values inline, with their standard errors when given; large ones as .npy blobs
    (or left out when put_blob is None)."""
    out = []
    for key, v in values.items():
        v = np.asarray(v, dtype=np.float32).ravel()
        shape = list(shapes.get(key, []))
        if v.size <= api.SMALL:
            out.append(pb.ParameterValue(key=key, value=v.tolist(), shape=shape,
                                         **standard_error(errors, key)))
        elif put_blob is not None:
            buf = io.BytesIO()
            np.save(buf, v.reshape(shape) if shape else v)
            out.append(pb.ParameterValue(key=key, shape=shape, blob=put_blob(buf.getvalue())))
    return out


# -- scenes -----------------------------------------------------------------------------------

def scene_input(main_file: str, files: dict[str, str], overrides: dict[str, str],
                display: str) -> api.SceneInput:
    """The engine's view of a scene: files by digest; ``key`` names exactly this content."""
    key = hashlib.sha256(json.dumps([main_file, sorted(files.items()), sorted(overrides.items())]
                                    ).encode()).hexdigest()[:32]
    return api.SceneInput(key, main_file, dict(files), dict(overrides), display)


def scene_input_to_json(s: api.SceneInput) -> str:
    return json.dumps({"main_file": s.main_file, "files": s.files, "overrides": s.overrides,
                       "display": s.display})


def scene_input_from_json(text: str) -> api.SceneInput:
    d = json.loads(text)
    return scene_input(d["main_file"], d["files"], d["overrides"], d["display"])


def parameter_to_pb(p: api.ParameterInfo) -> pb.Parameter:
    return pb.Parameter(key=p.key, kind=enums.parse(pb.ParameterKind, p.kind), shape=p.shape,
                        value=p.value, min=p.lo, max=p.hi,
                        default_learning_rate=p.learning_rate, discontinuous=p.discontinuous)


def sensors_to_pb(sensors: list[api.SensorInfo]) -> list[pb.Sensor]:
    return [pb.Sensor(index=s.index, id=s.id, width=s.width, height=s.height) for s in sensors]


def render_request(request: pb.RenderSceneRequest, read_blob: ReadBlob) -> api.RenderRequest:
    values = {}
    for v in request.parameters:
        array = value(v, read_blob, v.blob, v.value, f"value of '{v.key}'")
        if array is None:
            raise InvalidArgument(f"parameter '{v.key}' has neither values nor a blob")
        values[v.key] = array
    return api.RenderRequest(values, request.spp if request.HasField("spp") else 64,
                             list(request.sensors), request.seed)


def image_to_pb(image: api.Image, put_blob: PutBlob) -> pb.Image:
    return pb.Image(sensor=image.sensor, role=image.role, width=image.width,
                    height=image.height, exr_blob=put_blob(image.exr),
                    png_blob=put_blob(image.png), parameter=image.parameter)


# -- jobs -------------------------------------------------------------------------------------

def job_settings(spec: pb.JobSpec, scene: api.SceneInput, read_blob: ReadBlob,
                 max_samples: int = 0) -> api.JobSettings:
    """The engine's settings of a job whose spec was validated and defaulted; ``max_samples``
    is the daemon's limit on one render call (matoptd --max-samples)."""
    references = [api.ReferenceInput(r.sensor if r.HasField("sensor") else i,
                                     r.blob.removeprefix("blobs/"), r.filename or r.blob,
                                     r.mask_blob.removeprefix("blobs/"),
                                     r.mask_filename or r.mask_blob, r.alpha_mask)
                  for i, r in enumerate(spec.references)]
    parameters = [api.ParameterSetting(
        p.key, p.learning_rate, p.min, p.max,
        value(p, read_blob, p.initial_blob, p.initial_value, f"initial value of '{p.key}'"),
        p.smoothness)
        for p in spec.parameters]
    truth = {}
    for t in spec.ground_truth:
        v = value(t, read_blob, t.blob, t.value, f"ground truth of '{t.key}'")
        if v is not None:
            truth[t.key] = v
    return api.JobSettings(
        scene=scene, references=references, parameters=parameters,
        loss=enums.short_name(pb.Loss, spec.loss).lower(), iterations=spec.iterations,
        min_error=spec.min_error, spp=spec.spp, seed=spec.seed,
        cosine=spec.schedule != pb.SCHEDULE_CONSTANT, step_per_sensor=spec.sensor_mode == pb.SENSOR_MODE_STEP_PER_SENSOR,
        clamp=spec.clamp, resolution=spec.film_height, truth=truth,
        image_error_every=spec.image_error_every, image_error_spp=spec.image_error_spp or 64,
        fit_exposure=spec.fit_exposure, max_samples=max_samples)


def reference_names(spec: pb.JobSpec) -> dict[int, str]:
    """Each reference's file name by the sensor it belongs to, for the gains."""
    return {r.sensor if r.HasField("sensor") else i: r.filename or r.blob
            for i, r in enumerate(spec.references)}


def standard_error(errors: dict | None, key) -> dict:
    """The standard_error and interval fields of a value (none without an estimate)."""
    e = (errors or {}).get(key)
    if e is None:
        return {}
    return {"standard_error": np.asarray(e.error, dtype=np.float32).tolist(),
            "interval": [enums.parse(pb.Interval, r) for r in e.reading]}


def gains_to_pb(gains: dict[int, np.ndarray], names: dict[int, str],
                errors: dict[int, api.StandardError] | None = None
                ) -> list[pb.ReferenceGain]:
    return [pb.ReferenceGain(sensor=s, reference=names.get(s, ""),
                             rgb=np.asarray(g, dtype=np.float32).ravel().tolist(),
                             **standard_error(errors, s))
            for s, g in sorted(gains.items())]


def record_to_pb(r: api.IterationRecord, shapes: dict[str, list[int]],
                 names: dict[int, str] | None = None) -> pb.IterationRecord:
    """``names``: the reference file names by sensor (reference_names), for the gains."""
    out = pb.IterationRecord(
        iteration=r.iteration, seconds=r.seconds, loss=r.loss,
        parameters=values_to_pb(r.values, shapes, None),
        errors=[pb.ParameterError(key=k, max_abs=e.max_abs, rmse=e.rmse, relative=e.relative,
                                  psnr=e.psnr, correlation=e.correlation)
                for k, e in r.errors.items()],
        gains=gains_to_pb(r.gains, names or {}))
    if r.image_error is not None:
        out.image_error = r.image_error
    return out


def record_from_pb(r: pb.IterationRecord) -> api.IterationRecord:
    return api.IterationRecord(r.iteration, r.seconds, r.loss,
                               {v.key: np.asarray(v.value, dtype=np.float32)
                                for v in r.parameters if v.value},
                               {e.key: api.ParameterError(e.max_abs, e.rmse, e.relative, e.psnr,
                                                          list(e.correlation))
                                for e in r.errors})


def progress_to_job(job: pb.Job, p: api.Progress) -> None:
    """The job's figures after a step call."""
    last = p.records[-1]
    job.iteration, job.loss = last.iteration + 1, last.loss
    job.best_iteration = p.best_iteration
    job.best_loss = p.best_loss if math.isfinite(p.best_loss) else 0.0
    job.elapsed_seconds = p.seconds
    counters_to_job(job, p.counters)


def counters_to_job(job: pb.Job, c: api.Counters) -> None:
    job.nonfinite_gradient_steps = c.nonfinite_gradient_steps
    job.skipped_steps = c.skipped_steps
    job.clamped_components = c.clamped_components


def result_to_pb(job: str, r: api.Result, shapes: dict[str, list[int]], scene: pb.Scene,
                 put_blob: PutBlob, names: dict[int, str] | None = None) -> pb.JobResult:
    """The result, with the optimized scene as a bundle: the original files, and the new ones
    next to the main XML. ``names``: the reference file names by sensor, for the gains."""
    base = scene.main_file.rpartition("/")[0]
    new = {f"{base}/{path}" if base else path: put_blob(data)
           for path, data in r.scene_files.items()}
    out = pb.JobResult(job=job, which=enums.parse(pb.Which, r.which), iteration=r.iteration,
                       loss=r.loss,
                       parameters=values_to_pb(r.values, shapes, put_blob, r.standard_errors),
                       initial_parameters=values_to_pb(r.initial_values, shapes, put_blob),
                       images=[image_to_pb(i, put_blob) for i in r.images],
                       unplaced_parameters=r.unplaced,
                       gains=gains_to_pb(r.gains, names or {}, r.gain_errors))
    out.scene_files.extend(f for f in scene.files if f.path not in new)
    out.scene_files.extend(pb.BundleFile(path=p, sha256=b.removeprefix("blobs/"))
                           for p, b in new.items())
    out.scene_file = f"{base}/{r.scene_file}" if base else r.scene_file
    return out

"""Between the API's protobuf messages and the daemon's plain data: the records
(``records.py``), the settings (``settings.py``) and the engine's types (``engine_api``). The
only module that builds the API's messages from them; requests become plain data in
``job_spec.py`` (a JobSpec) and here (everything else).
"""

from __future__ import annotations

import collections

import numpy as np
from google.protobuf.timestamp_pb2 import Timestamp

from matopt_api import enums
from matopt_api.v1 import matopt_pb2 as pb

from .. import engine_api as api
from ..errors import InvalidArgument
from ..records import (BundleFile, ImageRef, JobRecord, Phase, ResultRecord, SceneRecord)
from ..scheduling.lanes import WorkerStatus
from ..settings import Values, read_values
from ..store.blobs import BlobEntry

STATES = {p: enums.parse(pb.JobState, p.state) for p in Phase}  # as the API shows them
END_PHASE = "end phase: "  # the note of a job in its end phase
WORKER_STATES = {"starting": pb.WORKER_STATE_STARTING, "idle": pb.WORKER_STATE_IDLE,
                 "busy": pb.WORKER_STATE_BUSY, "restarting": pb.WORKER_STATE_RESTARTING,
                 "failed": pb.WORKER_STATE_FAILED}


def phases(state: int) -> tuple[Phase, ...]:
    """The phases a ListJobs filter by ``state`` means (none: every job)."""
    return tuple(p for p, s in STATES.items() if s == state)


def timestamp(seconds: float) -> Timestamp:
    ts = Timestamp()
    ts.FromNanoseconds(int(seconds * 1e9))
    return ts


def blob(sha256: str) -> str:
    return f"blobs/{sha256}" if sha256 else ""


# -- values ----------------------------------------------------------------------------------

def values_to_pb(values: dict[str, Values], shapes: dict[str, list[int]],
                 errors: dict[str, api.StandardError] | None = None
                 ) -> list[pb.ParameterValue]:
    """With their standard errors where ``errors`` has them."""
    return [pb.ParameterValue(key=key, value=v.inline, shape=shapes.get(key, []),
                              blob=blob(v.sha256), **standard_error(errors, key))
            for key, v in values.items()]


def standard_error(errors: dict | None, key) -> dict:
    """The standard_error, interval and interval_reason fields of a value or gain (none
    without one)."""
    e = (errors or {}).get(key)
    if e is None:
        return {}
    return {"standard_error": np.asarray(e.error, dtype=np.float32).ravel().tolist(),
            "interval": [enums.parse(pb.Interval, r) for r in e.reading],
            "interval_reason": list(e.reason) if any(e.reason) else []}


def arrays_to_pb(values: dict[str, np.ndarray], shapes: dict[str, list[int]]
                 ) -> list[pb.ParameterValue]:
    """Small values (those a record carries) inline."""
    return [pb.ParameterValue(key=key, value=np.asarray(v, dtype=np.float32).ravel().tolist(),
                              shape=shapes.get(key, [])) for key, v in values.items()]


def given_values(inline, blob_name: str) -> Values | None:
    """Values a request gives inline or by blob; None when it gives neither."""
    if blob_name:
        return Values(sha256=blob_name.removeprefix("blobs/"))
    return Values(list(inline)) if len(inline) else None


# -- scenes ----------------------------------------------------------------------------------

def scene_to_pb(s: SceneRecord) -> pb.Scene:
    return pb.Scene(name=s.name, display_name=s.display_name, main_file=s.main_file,
                    files=[pb.BundleFile(path=f.path, sha256=f.sha256) for f in s.files],
                    overrides=s.overrides, sensors=[
                        pb.Sensor(index=x.index, id=x.id, width=x.width, height=x.height)
                        for x in s.sensors],
                    has_media=s.has_media, parameter_count=s.parameter_count,
                    warnings=s.warnings, create_time=timestamp(s.created))


def parameter_to_pb(p: api.ParameterInfo) -> pb.Parameter:
    return pb.Parameter(key=p.key, kind=enums.parse(pb.ParameterKind, p.kind), shape=p.shape,
                        value=p.value, min=p.lo, max=p.hi,
                        default_learning_rate=p.learning_rate, discontinuous=p.discontinuous)


def bundle_files(files) -> list[BundleFile]:
    return [BundleFile(f.path, f.sha256) for f in files]


def render_request(request: pb.RenderSceneRequest, read) -> api.RenderRequest:
    """``read``: digest -> bytes, the caller's blobs only."""
    values = {}
    for v in request.parameters:
        given = given_values(v.value, v.blob)
        if given is None:
            raise InvalidArgument(f"parameter '{v.key}' has neither values nor a blob")
        try:
            values[v.key] = read_values(given, read, f"value of '{v.key}'")
        except ValueError as exc:
            raise InvalidArgument(str(exc)) from None
    spp = {"spp": request.spp} if request.HasField("spp") else {}
    return api.RenderRequest(values, sensors=list(request.sensors), seed=request.seed, **spp)


def image_to_pb(i: ImageRef) -> pb.Image:
    return pb.Image(sensor=i.sensor, role=i.role, width=i.width, height=i.height,
                    exr_blob=blob(i.exr), png_blob=blob(i.png), parameter=i.parameter)


def blob_to_pb(b: BlobEntry) -> pb.Blob:
    return pb.Blob(name=blob(b.sha256), sha256=b.sha256, size_bytes=b.size, used_by=b.used_by)


# -- jobs ------------------------------------------------------------------------------------

def spec_to_pb(job: JobRecord) -> pb.JobSpec:
    """The job's settings as applied: every default filled in."""
    s = job.settings
    spec = pb.JobSpec(
        scene=job.scene,
        references=[pb.Reference(sensor=r.sensor, blob=blob(r.sha256), filename=r.name,
                                 mask_blob=blob(r.mask_sha256), mask_filename=r.mask_name,
                                 alpha_mask=r.alpha_mask) for r in s.references],
        parameters=[pb.ParameterSpec(
            key=p.key, learning_rate=p.learning_rate, min=p.lo, max=p.hi,
            initial_value=p.initial.inline if p.initial is not None else [],
            initial_blob=blob(p.initial.sha256) if p.initial is not None else "",
            smoothness=p.smoothness) for p in s.parameters],
        loss=enums.parse(pb.Loss, s.loss), iterations=s.iterations, min_error=s.min_error,
        spp=s.spp, seed=s.seed, schedule=enums.parse(pb.Schedule, s.schedule),
        sensor_mode=enums.parse(pb.SensorMode, s.sensor_mode), clamp=s.clamp,
        film_height=s.film_height, ground_truth=values_to_pb(s.truth, {}),
        image_error_every=s.image_error_every, image_error_spp=s.image_error_spp,
        fit_exposure=s.fit_exposure, choices=s.choices, spp_from=s.spp_from,
        large_steps_lambda=s.large_steps, starts=s.starts)
    if s.learning_rate is not None:
        spec.learning_rate = s.learning_rate
    return spec


def end_phase(job: JobRecord) -> str | None:
    """What a job in its end phase is doing, for its notes."""
    if job.phase is Phase.CANCELLING:
        return ("cancel requested: the job stops at its next iteration boundary, then renders "
                "its result images one sensor at a time (other jobs run in between) and ends "
                "CANCELLED")
    e = job.ending
    if job.phase is not Phase.ENDING or e is None:
        return None
    ended = (f"cancelled at iteration {job.iteration}" if e.outcome is Phase.CANCELLED
             else f"iterations over ({e.reason})")
    if not e.parts:
        return ended
    if e.next == "results":
        return f"{ended}: rendering result images {e.done}/{e.parts}"
    return (f"{ended}: result images rendered ({e.parts}); "
            + ("estimating standard errors" if e.next == "estimate" else "making its results"))


def job_to_pb(job: JobRecord) -> pb.Job:
    phase = end_phase(job)
    c = job.counters
    return pb.Job(
        name=job.name, spec=spec_to_pb(job), state=STATES[job.phase], owner=job.owner,
        iteration=job.iteration, loss=job.loss, best_iteration=job.best_iteration,
        best_loss=job.best_loss, elapsed_seconds=job.elapsed, integrator=job.integrator,
        integrator_reason=job.integrator_reason, sensors_rendered=job.sensors,
        nonfinite_gradient_steps=c.nonfinite_gradient_steps, skipped_steps=c.skipped_steps,
        error=job.error, stop_reason=job.stop_reason, resumed_from=job.resumed_from,
        create_time=timestamp(job.created), update_time=timestamp(job.updated),
        notes=job.notes + ([END_PHASE + phase] if phase else []),
        clamped_components=c.clamped_components, worker=job.worker,
        choices=[pb.Choice(name=x.name, on=x.on, why=x.why,
                           seconds_per_iteration=x.seconds_per_iteration,
                           setup_seconds=x.setup_seconds, switchable=x.switchable)
                 for x in job.choices],
        best_parameters=values_to_pb(job.best_values, job.shapes, job.best_errors))


def reference_names(job: JobRecord) -> dict[int, str]:
    """Each reference's file name by the sensor it belongs to, for the gains."""
    return {r.sensor: r.name for r in job.settings.references}


def gains_to_pb(gains: dict[int, np.ndarray] | dict[int, list[float]], names: dict[int, str],
                errors: dict[int, api.StandardError] | None = None
                ) -> list[pb.ReferenceGain]:
    return [pb.ReferenceGain(sensor=s, reference=names.get(s, ""),
                             rgb=np.asarray(g, dtype=np.float32).ravel().tolist(),
                             **standard_error(errors, s))
            for s, g in sorted(gains.items())]


def iteration_to_pb(r: api.IterationRecord, job: JobRecord) -> pb.IterationRecord:
    out = pb.IterationRecord(
        iteration=r.iteration, seconds=r.seconds, loss=r.loss,
        parameters=arrays_to_pb(r.values, job.shapes),
        errors=[pb.ParameterError(key=k, max_abs=e.max_abs, rmse=e.rmse, relative=e.relative,
                                  psnr=e.psnr, correlation=e.correlation)
                for k, e in r.errors.items()],
        gains=gains_to_pb(r.gains, reference_names(job)), spp=r.spp)
    if r.image_error is not None:
        out.image_error = r.image_error
    return out


def result_to_pb(r: ResultRecord, job: JobRecord) -> pb.JobResult:
    return pb.JobResult(
        job=r.job, which=enums.parse(pb.Which, r.which), iteration=r.iteration, loss=r.loss,
        parameters=values_to_pb(r.values, r.shapes, r.standard_errors),
        initial_parameters=values_to_pb(r.initial, r.shapes),
        images=[image_to_pb(i) for i in r.images],
        scene_files=[pb.BundleFile(path=f.path, sha256=f.sha256) for f in r.scene_files],
        scene_file=r.scene_file, unplaced_parameters=r.unplaced,
        gains=gains_to_pb(r.gains, reference_names(job), r.gain_errors))


def event_to_pb(event: JobRecord | api.IterationRecord, job: JobRecord) -> pb.JobEvent:
    """A watcher's event; ``job``: the job as the watcher last saw it (shapes and names for
    an iteration's values and gains)."""
    if isinstance(event, JobRecord):
        return pb.JobEvent(job=job_to_pb(event))
    return pb.JobEvent(iteration=iteration_to_pb(event, job))


class Converted:
    """The message each record or event became, by the object's identity: the store hands
    every status call the same record until the job changes, and the events hand every
    watcher the same objects, so hundreds of calls a second cost one conversion per change.
    The messages are shared: nothing changes them once built."""

    def __init__(self, kept: int = 256) -> None:  # the latest of each job polled or watched
        self.kept = kept
        # (kind, id) -> (the object, kept so that its id is not reused, and its message)
        self._built: collections.OrderedDict[tuple[str, int], tuple[object, object]] = \
            collections.OrderedDict()

    def job(self, job: JobRecord) -> pb.Job:
        return self._get("job", job, lambda: job_to_pb(job))

    def event(self, event: JobRecord | api.IterationRecord, job: JobRecord) -> pb.JobEvent:
        return self._get("event", event, lambda: event_to_pb(event, job))

    def _get(self, kind: str, source: object, build):
        key = (kind, id(source))
        built = self._built.get(key)
        if built is None or built[0] is not source:
            built = self._built[key] = (source, build())
            if len(self._built) > self.kept:
                self._built.popitem(last=False)
        return built[1]


# -- workers ---------------------------------------------------------------------------------

def worker_to_pb(w: WorkerStatus) -> pb.Worker:
    return pb.Worker(name=w.name, state=WORKER_STATES[w.state], variant=w.variant,
                     device=w.device, host=w.host, pid=w.pid, jobs=w.jobs,
                     job_count=w.job_count, restarts=w.restarts, last_exit=w.last_exit,
                     memory_bytes=w.memory, memory_limit_bytes=w.memory_limit,
                     threads=w.threads, node=w.node, sizing=w.sizing)

"""The database's schema, and data dirs of earlier releases brought to it when the store opens.

Version 2 (this one; ``PRAGMA user_version`` 2) keeps the records of ``records.py`` as JSON.
Version 1, every release before it (user_version 0), kept the API's protobuf messages in its
rows: a Scene and its ListSceneParametersResponse, a Job with its spec (every default filled
in but sensor_mode and image_error_spp), IterationRecords and JobResults; its first release
lacked ``scenes.inputs`` and kept checkpoints as blobs named by ``jobs.checkpoint``. Reading
that format is this module's alone, which is why it imports the protobuf stubs.

The upgrade is one transaction: a crash halfway leaves the data dir as it was, and the next
start does it again. What version 1 never recorded is filled in as well as can be known: a
job's parameter shapes from its scene's listing; the iteration of its latest checkpoint is
unknown; an unfinished job whose scene cannot be loaded any more (made before scenes kept what
a worker loads, or deleted) fails with a message that says so.
"""

from __future__ import annotations

import json
import logging
import sqlite3

import numpy as np
from matopt_api import enums
from matopt_api.v1 import matopt_pb2 as pb

from ..engine_api import (ChoiceStatus, Counters, IterationRecord, ParameterInfo, SensorInfo,
                          StandardError)
from ..records import (BundleFile, ImageRef, JobRecord, Phase, ResultRecord, SceneRecord,
                       RESUME_PENDING)
from ..settings import JobSettings, ParameterSetting, ReferenceInput, SceneInput, Values
from ..truth import ParameterError
from . import codec
from .blobs import Blobs
from .checkpoints import Checkpoints
from .database import Database

log = logging.getLogger("matoptd.store")

VERSION = 2
SCHEMA = (
    "CREATE TABLE scenes (name TEXT PRIMARY KEY, owner TEXT NOT NULL, request_id TEXT, "
    "seq INTEGER NOT NULL, record TEXT NOT NULL, parameters TEXT NOT NULL)",
    "CREATE UNIQUE INDEX scenes_request ON scenes(owner, request_id) "
    "WHERE request_id IS NOT NULL",
    "CREATE TABLE jobs (name TEXT PRIMARY KEY, owner TEXT NOT NULL, request_id TEXT, "
    "seq INTEGER NOT NULL, phase TEXT NOT NULL, settings TEXT NOT NULL, record TEXT NOT NULL)",
    "CREATE UNIQUE INDEX jobs_request ON jobs(owner, request_id) WHERE request_id IS NOT NULL",
    "CREATE INDEX jobs_owner ON jobs(owner, phase)",
    "CREATE TABLE iterations (job TEXT NOT NULL, iteration INTEGER NOT NULL, "
    "record TEXT NOT NULL, PRIMARY KEY (job, iteration))",
    "CREATE TABLE results (job TEXT NOT NULL, which TEXT NOT NULL, record TEXT NOT NULL, "
    "PRIMARY KEY (job, which))",
)
LEGACY_TABLES = ("scenes", "jobs", "iterations", "results")

_PHASES = {pb.JOB_STATE_QUEUED: Phase.QUEUED, pb.JOB_STATE_RUNNING: Phase.RUNNING,
           pb.JOB_STATE_PAUSED: Phase.PAUSED, pb.JOB_STATE_SUCCEEDED: Phase.SUCCEEDED,
           pb.JOB_STATE_FAILED: Phase.FAILED, pb.JOB_STATE_CANCELLED: Phase.CANCELLED,
           pb.JOB_STATE_INTERRUPTED: Phase.INTERRUPTED}
_END_PHASE = "end phase: "  # version 1's note of a job in its end phase


def upgrade(db: Database, blobs: Blobs, checkpoints: Checkpoints) -> None:
    version = db.query("PRAGMA user_version")[0][0]
    if version > VERSION:
        raise RuntimeError(f"the data dir's database is of version {version}, made by a newer "
                           f"matoptd; this one reads up to version {VERSION}")
    if version == VERSION:
        return
    legacy = "jobs" in db.tables()
    with db.transaction() as c:
        if legacy:
            for table in LEGACY_TABLES:
                c.execute(f"ALTER TABLE {table} RENAME TO legacy_{table}")
            for index in ("scenes_request", "jobs_request"):
                c.execute(f"DROP INDEX IF EXISTS {index}")
        for sql in SCHEMA:
            c.execute(sql)
        if legacy:
            counts = _from_protobuf(c, blobs, checkpoints)
            for table in LEGACY_TABLES:
                c.execute(f"DROP TABLE legacy_{table}")
        c.execute(f"PRAGMA user_version={VERSION}")
    if legacy:
        log.info("data dir upgraded to version %d: %s", VERSION,
                 ", ".join(f"{n} {what}" for what, n in counts.items()))


def _from_protobuf(c: sqlite3.Connection, blobs: Blobs, checkpoints: Checkpoints
                   ) -> dict[str, int]:
    columns = [r[1] for r in c.execute("PRAGMA table_info(legacy_scenes)")]
    inputs_column = "inputs" if "inputs" in columns else "NULL"
    scenes: dict[str, SceneRecord] = {}
    listings: dict[str, list[ParameterInfo]] = {}
    for name, owner, request_id, seq, scene, parameters, inputs in c.execute(
            f"SELECT name, owner, request_id, seq, scene, parameters, {inputs_column} "
            "FROM legacy_scenes").fetchall():
        record = scene_record(pb.Scene.FromString(scene), owner, inputs)
        listing = [parameter_info(p) for p in
                   pb.ListSceneParametersResponse.FromString(parameters).parameters]
        scenes[name], listings[name] = record, listing
        c.execute("INSERT INTO scenes VALUES (?, ?, ?, ?, ?, ?)",
                  (name, owner, request_id, seq, codec.dumps(record), codec.dumps(listing)))
    jobs = 0
    for name, owner, request_id, seq, job, checkpoint in c.execute(
            "SELECT name, owner, request_id, seq, job, checkpoint FROM legacy_jobs").fetchall():
        message = pb.Job.FromString(job)
        record = job_record(message, owner, scenes.get(message.spec.scene),
                            listings.get(message.spec.scene, []))
        status = codec.encode(record)
        settings = status.pop("settings")
        c.execute("INSERT INTO jobs VALUES (?, ?, ?, ?, ?, ?, ?)",
                  (name, owner, request_id, seq, record.phase.value, json.dumps(settings),
                   json.dumps(status)))
        if checkpoint and not checkpoints.exists(name):  # the first release's, as a blob
            try:
                checkpoints.write(name, blobs.read(checkpoint))
            except Exception as exc:  # noqa: BLE001 - the job resumes from the start then
                log.warning("%s: its checkpoint %s could not be kept: %s", name, checkpoint,
                            exc)
        jobs += 1
    iterations = 0
    for job, iteration, record in c.execute(
            "SELECT job, iteration, record FROM legacy_iterations").fetchall():
        c.execute("INSERT INTO iterations VALUES (?, ?, ?)",
                  (job, iteration, codec.dumps(iteration_record(
                      pb.IterationRecord.FromString(record)))))
        iterations += 1
    results = 0
    for job, which, result in c.execute(
            "SELECT job, which, result FROM legacy_results").fetchall():
        record = result_record(pb.JobResult.FromString(result))
        c.execute("INSERT INTO results VALUES (?, ?, ?)",
                  (job, record.which, codec.dumps(record)))
        results += 1
    return {"scenes": len(scenes), "jobs": jobs, "iteration records": iterations,
            "results": results}


# -- version 1's messages as records ----------------------------------------------------------

def _seconds(ts) -> float:
    return ts.seconds + ts.nanos / 1e9


def _bare(blob: str) -> str:
    return blob.removeprefix("blobs/")


def _values(inline, blob: str) -> Values | None:
    if blob:
        return Values(sha256=_bare(blob))
    return Values(list(inline)) if len(inline) else None


def _standard_errors(values, key=lambda v: v.key) -> dict:
    """The standard errors of values (or gains) that carry them."""
    return {key(v): StandardError(np.asarray(v.standard_error, dtype=np.float32),
                                  [enums.short_name(pb.Interval, i).lower() for i in v.interval])
            for v in values if len(v.standard_error)}


def _name(enum, value: int, default: str) -> str:
    return enums.short_name(enum, value).lower() if value else default


def scene_record(scene: pb.Scene, owner: str, inputs: str | None) -> SceneRecord:
    given = json.loads(inputs) if inputs else None
    return SceneRecord(
        name=scene.name, owner=owner, display_name=scene.display_name,
        main_file=scene.main_file,
        files=[BundleFile(f.path, f.sha256) for f in scene.files],
        overrides=dict(scene.overrides), warnings=list(scene.warnings),
        sensors=[SensorInfo(s.index, s.id, s.width, s.height) for s in scene.sensors],
        has_media=scene.has_media, parameter_count=scene.parameter_count,
        inputs=SceneInput.of(given["main_file"], given["files"], given["overrides"],
                             given["display"]) if given else None,
        created=_seconds(scene.create_time))


def parameter_info(p: pb.Parameter) -> ParameterInfo:
    return ParameterInfo(p.key, _name(pb.ParameterKind, p.kind, "vector"), list(p.shape),
                         list(p.value), p.min, p.max, p.default_learning_rate,
                         p.discontinuous)


def job_settings(spec: pb.JobSpec, scene: SceneInput) -> JobSettings:
    defaults = JobSettings(scene, [], [])
    truth = {t.key: _values(t.value, t.blob) for t in spec.ground_truth}
    return JobSettings(
        scene=scene,
        references=[ReferenceInput(r.sensor if r.HasField("sensor") else i, _bare(r.blob),
                                   r.filename or r.blob, _bare(r.mask_blob),
                                   r.mask_filename or r.mask_blob, r.alpha_mask)
                    for i, r in enumerate(spec.references)],
        parameters=[ParameterSetting(p.key, p.learning_rate, p.min, p.max,
                                     _values(p.initial_value, p.initial_blob), p.smoothness)
                    for p in spec.parameters],
        loss=_name(pb.Loss, spec.loss, defaults.loss),
        iterations=spec.iterations if spec.HasField("iterations") else defaults.iterations,
        min_error=spec.min_error if spec.HasField("min_error") else defaults.min_error,
        spp=spec.spp if spec.HasField("spp") else defaults.spp, seed=spec.seed,
        learning_rate=spec.learning_rate if spec.HasField("learning_rate") else None,
        schedule=_name(pb.Schedule, spec.schedule, defaults.schedule),
        sensor_mode=_name(pb.SensorMode, spec.sensor_mode, defaults.sensor_mode),
        clamp=spec.clamp, film_height=spec.film_height,
        truth={k: v for k, v in truth.items() if v is not None},
        image_error_every=spec.image_error_every,
        image_error_spp=spec.image_error_spp or defaults.image_error_spp,
        fit_exposure=spec.fit_exposure, choices=dict(spec.choices))


def job_record(job: pb.Job, owner: str, scene: SceneRecord | None,
               listing: list[ParameterInfo]) -> JobRecord:
    loadable = scene is not None and scene.inputs is not None
    inputs = scene.inputs if loadable else SceneInput(
        "", "", {}, {}, scene.display_name if scene is not None else job.spec.scene)
    phase = _PHASES.get(job.state, Phase.FAILED)
    shapes = {p.key: list(p.shape) for p in listing}
    record = JobRecord(
        name=job.name, owner=owner, scene=job.spec.scene,
        settings=job_settings(job.spec, inputs), phase=phase,
        created=_seconds(job.create_time), updated=_seconds(job.update_time),
        iteration=job.iteration, loss=job.loss, best_iteration=job.best_iteration,
        best_loss=job.best_loss, elapsed=job.elapsed_seconds,
        counters=Counters(job.nonfinite_gradient_steps, job.skipped_steps,
                          job.clamped_components),
        integrator=job.integrator, integrator_reason=job.integrator_reason,
        sensors=list(job.sensors_rendered),
        shapes={p.key: shapes.get(p.key, []) for p in job.spec.parameters},
        worker=job.worker, resumed_from=job.resumed_from, error=job.error,
        stop_reason=job.stop_reason,
        notes=[n for n in job.notes if not n.startswith(_END_PHASE)],
        choices=[ChoiceStatus(c.name, c.on, c.why, c.seconds_per_iteration, c.setup_seconds,
                              c.switchable) for c in job.choices],
        best_values={v.key: Values(list(v.value)) for v in job.best_parameters},
        best_errors=_standard_errors(job.best_parameters))
    if not loadable and not phase.final:
        record.phase, record.stop_reason = Phase.FAILED, "failed"
        record.error = (f"its scene '{job.spec.scene}' cannot be loaded any more (it was made "
                        "by an older matoptd, or deleted): create the scene again and start a "
                        "new job")
    if record.resumed_from == RESUME_PENDING and phase.final:
        record.resumed_from = ""
    return record


def iteration_record(r: pb.IterationRecord) -> IterationRecord:
    return IterationRecord(
        r.iteration, r.seconds, r.loss,
        {v.key: np.asarray(v.value, dtype=np.float32) for v in r.parameters if v.value},
        {e.key: ParameterError(e.max_abs, e.rmse, e.relative, e.psnr, list(e.correlation))
         for e in r.errors},
        r.image_error if r.HasField("image_error") else None,
        {g.sensor: np.asarray(g.rgb, dtype=np.float32) for g in r.gains}, r.spp)


def _image(i: pb.Image) -> ImageRef:
    return ImageRef(i.sensor, i.role, i.width, i.height, _bare(i.exr_blob), _bare(i.png_blob),
                    i.parameter)


def result_record(r: pb.JobResult) -> ResultRecord:
    return ResultRecord(
        job=r.job, which=_name(pb.Which, r.which, "best"), iteration=r.iteration, loss=r.loss,
        values={v.key: _values(v.value, v.blob) or Values() for v in r.parameters},
        initial={v.key: _values(v.value, v.blob) or Values() for v in r.initial_parameters},
        shapes={v.key: list(v.shape) for v in (*r.initial_parameters, *r.parameters)},
        images=[_image(i) for i in r.images],
        scene_files=[BundleFile(f.path, f.sha256) for f in r.scene_files],
        scene_file=r.scene_file, unplaced=list(r.unplaced_parameters),
        standard_errors=_standard_errors(r.parameters),
        gain_errors=_standard_errors(r.gains, key=lambda g: g.sensor),
        gains={g.sensor: list(g.rgb) for g in r.gains})

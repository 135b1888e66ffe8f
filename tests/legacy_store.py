"""Writes a data dir's database as every release up to the JSON records kept it (schema version
1, ``PRAGMA user_version`` 0): rows of the API's protobuf messages, as those releases stored
exactly what GetScene, ListSceneParameters, GetJob, GetJobHistory and GetJobResult answered.

``write`` takes those answers (read from a running daemon) and the scenes' worker inputs, and
puts them in the old tables, with what the old daemon left out of a job's spec left out again
(sensor_mode, image_error_spp, each reference's sensor): a migration must fill them in. The
schema below is the old store's own, as it was.
"""

from __future__ import annotations

import json
import sqlite3
from dataclasses import dataclass, field
from pathlib import Path

from matopt_api.v1 import matopt_pb2 as pb

SCHEMA = """
CREATE TABLE IF NOT EXISTS scenes (
    name TEXT PRIMARY KEY, owner TEXT NOT NULL, request_id TEXT, seq INTEGER NOT NULL,
    scene BLOB NOT NULL, parameters BLOB NOT NULL);
CREATE UNIQUE INDEX IF NOT EXISTS scenes_request ON scenes(owner, request_id)
    WHERE request_id IS NOT NULL;
CREATE TABLE IF NOT EXISTS jobs (
    name TEXT PRIMARY KEY, owner TEXT NOT NULL, request_id TEXT, seq INTEGER NOT NULL,
    state INTEGER NOT NULL, job BLOB NOT NULL, checkpoint TEXT);
CREATE UNIQUE INDEX IF NOT EXISTS jobs_request ON jobs(owner, request_id)
    WHERE request_id IS NOT NULL;
CREATE TABLE IF NOT EXISTS iterations (
    job TEXT NOT NULL, iteration INTEGER NOT NULL, record BLOB NOT NULL,
    PRIMARY KEY (job, iteration));
CREATE TABLE IF NOT EXISTS results (
    job TEXT NOT NULL, which INTEGER NOT NULL, result BLOB NOT NULL,
    PRIMARY KEY (job, which));
ALTER TABLE scenes ADD COLUMN inputs TEXT;
CREATE TABLE blob_owners (sha256 TEXT NOT NULL, owner TEXT NOT NULL,
    size INTEGER NOT NULL, PRIMARY KEY (sha256, owner));
CREATE INDEX blob_owners_owner ON blob_owners(owner);
"""


@dataclass
class Answers:
    """What the daemon answered about a user's scenes and jobs."""

    owner: str
    scenes: list[tuple[pb.Scene, pb.ListSceneParametersResponse]] = field(default_factory=list)
    jobs: list[pb.Job] = field(default_factory=list)
    histories: dict[str, list[pb.IterationRecord]] = field(default_factory=dict)
    results: list[pb.JobResult] = field(default_factory=list)


def old_spec(job: pb.Job) -> pb.Job:
    """The job as the old daemon stored it: without the defaults it did not fill in."""
    old = pb.Job()
    old.CopyFrom(job)
    old.spec.sensor_mode = 0
    if old.spec.image_error_spp == 64:
        old.spec.image_error_spp = 0
    for r in old.spec.references:
        r.ClearField("sensor")
    return old


def write(data_dir: Path, answers: Answers, inputs: dict[str, dict],
          owners: list[tuple[str, str, int]], states: dict[str, int] | None = None,
          checkpoint_blobs: dict[str, str] | None = None) -> None:
    """Replaces the data dir's database with the old one. ``inputs``: each scene's worker
    inputs (main_file, files, overrides, display); ``owners``: the blob_owners rows;
    ``states``: a job state to store instead of the answered one (a daemon that crashed while
    the job ran); ``checkpoint_blobs``: jobs whose checkpoint the first release kept as a blob
    (its name in jobs.checkpoint)."""
    for suffix in ("", "-wal", "-shm"):
        (data_dir / f"matoptd.sqlite3{suffix}").unlink(missing_ok=True)
    db = sqlite3.connect(data_dir / "matoptd.sqlite3")
    db.executescript(SCHEMA)
    for seq, (scene, parameters) in enumerate(answers.scenes, 1):
        db.execute("INSERT INTO scenes VALUES (?, ?, NULL, ?, ?, ?, ?)",
                   (scene.name, answers.owner, seq, scene.SerializeToString(),
                    parameters.SerializeToString(), json.dumps(inputs[scene.name])))
    for seq, job in enumerate(answers.jobs, 1):
        state = (states or {}).get(job.name, job.state)
        old = old_spec(job)
        old.state = state
        db.execute("INSERT INTO jobs VALUES (?, ?, NULL, ?, ?, ?, ?)",
                   (job.name, answers.owner, seq, state, old.SerializeToString(),
                    (checkpoint_blobs or {}).get(job.name)))
    for name, records in answers.histories.items():
        db.executemany("INSERT INTO iterations VALUES (?, ?, ?)",
                       [(name, r.iteration, r.SerializeToString()) for r in records])
    db.executemany("INSERT INTO results VALUES (?, ?, ?)",
                   [(r.job, r.which, r.SerializeToString()) for r in answers.results])
    db.executemany("INSERT INTO blob_owners VALUES (?, ?, ?)", owners)
    db.commit()
    db.close()

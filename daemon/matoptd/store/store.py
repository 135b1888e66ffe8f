"""Everything that must survive a daemon restart: the records (scenes, jobs, their iteration
histories and results) in SQLite, the blobs and the checkpoints, under --data-dir.

Rows hold the records of ``records.py`` as JSON (``codec``), with the columns lookups need
(owner, phase, request_id) beside them; a job's settings are a column of their own, written
once, since they never change while its status changes every step. A data dir of an earlier
release is brought to this form when the store opens (``migrate``).
"""

from __future__ import annotations

import collections
import dataclasses
import json
import threading
from pathlib import Path
from typing import Iterable, Iterator

from ..engine_api import IterationRecord, ParameterInfo
from ..errors import NotFound
from ..records import JobRecord, Phase, ResultRecord, SceneRecord
from ..settings import JobSettings
from . import blob_refs, codec, migrate
from .blobs import Blobs
from .checkpoints import Checkpoints
from .database import Database
from .disk import Disk

CHUNK = 1 << 20  # bytes per message when a blob is streamed
SETTINGS_KEPT = 4096  # jobs whose settings stay decoded (status calls read them again and again)
RECORDS_KEPT = 4096   # jobs whose latest record stays in memory, decoded once it is read


class Store:
    def __init__(self, data_dir: Path, quota: int | None = None) -> None:
        """``quota``: the bytes of blobs each user may own (None: no limit)."""
        self.root = Path(data_dir)
        self.disk = Disk(self.root)
        self.db = Database(self.root / "matoptd.sqlite3", self.disk)
        self.checkpoints = Checkpoints(self.root / "checkpoints", self.disk)
        self.blobs = Blobs(self.root / "blobs", self.db, self.disk, quota, self._uses)
        migrate.upgrade(self.db, self.blobs, self.checkpoints)
        # A job's settings never change once written: each is decoded once and shared (they
        # are frozen; nothing changes them in place).
        self._settings: collections.OrderedDict[str, JobSettings] = collections.OrderedDict()
        # Each job's latest row as written (owner, settings, status text) and, once read, its
        # record: a status call (hundreds a second) then costs neither SQL nor JSON. Written
        # through under ``_lock``, so that the row and the kept copy never disagree.
        self._records: collections.OrderedDict[str, _Kept] = collections.OrderedDict()
        self._lock = threading.Lock()
        if "blob_owners" not in self.db.tables():
            self.blobs.adopt(self._uses(None))

    def close(self) -> None:
        self.db.close()

    # -- scenes -----------------------------------------------------------------------------

    def add_scene(self, scene: SceneRecord, parameters: list[ParameterInfo],
                  request_id: str | None) -> None:
        self.db.execute(
            "INSERT INTO scenes (name, owner, request_id, seq, record, parameters) VALUES "
            "(?, ?, ?, (SELECT COALESCE(MAX(seq),0)+1 FROM scenes), ?, ?)",
            (scene.name, scene.owner, request_id or None, codec.dumps(scene),
             codec.dumps(parameters)))

    def scene_by_request(self, owner: str, request_id: str) -> SceneRecord | None:
        rows = self.db.query("SELECT record FROM scenes WHERE owner=? AND request_id=?",
                             (owner, request_id))
        return codec.loads(SceneRecord, rows[0][0]) if rows else None

    def get_scene(self, owner: str, name: str) -> SceneRecord:
        rows = self.db.query("SELECT record FROM scenes WHERE name=? AND owner=?",
                             (name, owner))
        if not rows:
            raise NotFound(f"scene '{name}' not found")
        return codec.loads(SceneRecord, rows[0][0])

    def scene_parameters(self, owner: str, name: str) -> list[ParameterInfo]:
        rows = self.db.query("SELECT parameters FROM scenes WHERE name=? AND owner=?",
                             (name, owner))
        if not rows:
            raise NotFound(f"scene '{name}' not found")
        return codec.loads(list[ParameterInfo], rows[0][0])

    def list_scenes(self, owner: str, offset: int, limit: int) -> list[SceneRecord]:
        rows = self.db.query("SELECT record FROM scenes WHERE owner=? ORDER BY seq LIMIT ? "
                             "OFFSET ?", (owner, limit, offset))
        return [codec.loads(SceneRecord, r[0]) for r in rows]

    def delete_scene(self, owner: str, name: str) -> None:
        self.get_scene(owner, name)
        self.db.execute("DELETE FROM scenes WHERE name=?", (name,))

    # -- jobs -------------------------------------------------------------------------------

    def add_job(self, job: JobRecord, request_id: str | None) -> None:
        settings, status = codec.dumps(job.settings), _status(job)
        with self._lock:
            self.db.execute(
                "INSERT INTO jobs (name, owner, request_id, seq, phase, settings, record) "
                "VALUES (?, ?, ?, (SELECT COALESCE(MAX(seq),0)+1 FROM jobs), ?, ?, ?)",
                (job.name, job.owner, request_id or None, job.phase.value, settings, status))
            self._keep(_Kept(job.name, job.owner, settings, status))

    def put_job(self, job: JobRecord) -> None:
        """The job's record as it stands (its settings were written by ``add_job``)."""
        status = _status(job)
        with self._lock:
            self.db.execute("UPDATE jobs SET phase=?, record=? WHERE name=?",
                            (job.phase.value, status, job.name))
            kept = self._records.get(job.name)
            if kept is not None:
                self._keep(_Kept(job.name, job.owner, kept.settings, status))

    def job_by_request(self, owner: str, request_id: str) -> JobRecord | None:
        rows = self.db.query("SELECT name, settings, record FROM jobs WHERE owner=? AND "
                             "request_id=?", (owner, request_id))
        return self._job(*rows[0]) if rows else None

    def get_job(self, name: str, owner: str | None = None) -> JobRecord:
        """A job by name; with ``owner``, another user's job is NOT_FOUND, as if absent.
        The record is shared with every other reader until the job changes: take a
        ``snapshot()`` to change it."""
        with self._lock:
            kept = self._records.get(name)
            if kept is None:
                rows = self.db.query("SELECT name, owner, settings, record FROM jobs "
                                     "WHERE name=?", (name,))
                if not rows:
                    raise NotFound(f"job '{name}' not found")
                kept = self._keep(_Kept(*rows[0]))
            if owner is not None and kept.owner != owner:
                raise NotFound(f"job '{name}' not found")
            if kept.record is None:
                kept.record = self._job(name, kept.settings, kept.status)
            return kept.record

    def _keep(self, kept: _Kept) -> _Kept:
        self._records[kept.name] = kept
        self._records.move_to_end(kept.name)
        if len(self._records) > RECORDS_KEPT:
            self._records.popitem(last=False)
        return kept

    def list_jobs(self, owner: str | None, offset: int = 0, limit: int = -1,
                  phases: Iterable[Phase] = ()) -> list[JobRecord]:
        sql, args = "SELECT name, settings, record FROM jobs WHERE 1=1", []
        if owner is not None:
            sql += " AND owner=?"
            args.append(owner)
        phases = [p.value for p in phases]
        if phases:
            sql += f" AND phase IN ({','.join('?' * len(phases))})"
            args += phases
        sql += " ORDER BY seq LIMIT ? OFFSET ?"
        return [self._job(*r) for r in self.db.query(sql, (*args, limit, offset))]

    def count_jobs(self, owner: str, phases: Iterable[Phase]) -> int:
        values = [p.value for p in phases]
        return self.db.query(
            f"SELECT COUNT(*) FROM jobs WHERE owner=? AND phase IN "
            f"({','.join('?' * len(values))})", (owner, *values))[0][0]

    def count_by_phase(self) -> dict[Phase, int]:
        """Every user's jobs by phase (a phase without any: 0)."""
        counts = dict(self.db.query("SELECT phase, COUNT(*) FROM jobs GROUP BY phase"))
        return {p: counts.get(p.value, 0) for p in Phase}

    def delete_job(self, name: str) -> None:
        with self._lock, self.db.transaction() as db:
            for table, col in (("jobs", "name"), ("iterations", "job"), ("results", "job")):
                db.execute(f"DELETE FROM {table} WHERE {col}=?", (name,))
            self._records.pop(name, None)
        self.checkpoints.delete(name)
        self._settings.pop(name, None)

    # -- histories and results --------------------------------------------------------------

    def add_iterations(self, job: str, records: list[IterationRecord]) -> None:
        with self.db.transaction() as db:
            for r in records:
                db.execute("INSERT OR REPLACE INTO iterations VALUES (?, ?, ?)",
                           (job, r.iteration, codec.dumps(r)))

    def history(self, job: str, offset: int = 0, limit: int = -1) -> list[IterationRecord]:
        """Records in iteration order; a page of them with ``offset`` and ``limit``."""
        rows = self.db.query("SELECT record FROM iterations WHERE job=? ORDER BY iteration "
                             "LIMIT ? OFFSET ?", (job, limit, offset))
        decode = codec.decoder(IterationRecord)
        return [decode(json.loads(r[0])) for r in rows]

    def truncate_history(self, job: str, keep_below: int) -> None:
        """Forgets iterations from ``keep_below`` on (they will be run again after a resume)."""
        self.db.execute("DELETE FROM iterations WHERE job=? AND iteration>=?",
                        (job, keep_below))

    def put_result(self, result: ResultRecord) -> None:
        self.db.execute("INSERT OR REPLACE INTO results VALUES (?, ?, ?)",
                        (result.job, result.which, codec.dumps(result)))

    def result(self, job: str, which: str) -> ResultRecord | None:
        rows = self.db.query("SELECT record FROM results WHERE job=? AND which=?",
                             (job, which))
        return codec.loads(ResultRecord, rows[0][0]) if rows else None

    # -- what names which blob --------------------------------------------------------------

    def _uses(self, owner: str | None) -> Iterator[tuple[str, str, set[str]]]:
        """(owner, scene or job name, the digests it names) for every scene and job, or
        ``owner``'s."""
        where, args = (" WHERE owner=?", (owner,)) if owner is not None else ("", ())
        for (text,) in self.db.query("SELECT record FROM scenes" + where, args):
            scene = codec.loads(SceneRecord, text)
            yield scene.owner, scene.name, blob_refs.scene_blobs(scene)
        results: dict[str, list[ResultRecord]] = {}
        for job, text in self.db.query("SELECT job, record FROM results WHERE job IN "
                                       "(SELECT name FROM jobs" + where + ")", args):
            results.setdefault(job, []).append(codec.loads(ResultRecord, text))
        for name, settings, status in self.db.query(
                "SELECT name, settings, record FROM jobs" + where, args):
            job = self._job(name, settings, status)
            yield job.owner, job.name, blob_refs.job_blobs(job, results.get(job.name, ()))

    def _job(self, name: str, settings: str, status: str) -> JobRecord:
        """The record of a row: its settings decoded once (see ``_settings``)."""
        kept = self._settings.get(name)
        if kept is None:
            kept = self._settings[name] = codec.loads(JobSettings, settings)
            if len(self._settings) > SETTINGS_KEPT:
                self._settings.popitem(last=False)
        record = json.loads(status)
        record["settings"] = kept
        return codec.decoder(JobRecord)(record)



@dataclasses.dataclass
class _Kept:
    """A job's row as the store last wrote or read it; ``record`` decoded on first read."""

    name: str
    owner: str
    settings: str
    status: str
    record: JobRecord | None = None


def _status(job: JobRecord) -> str:
    """The record without its settings, which have a column of their own."""
    return codec.dumps({f.name: getattr(job, f.name) for f in dataclasses.fields(job)
                        if f.name != "settings"})

"""Everything that must survive a daemon restart: an SQLite database of scenes, jobs, their
iteration histories, results and checkpoints, and content-addressed blobs on disk.

Rows hold the serialized protobuf messages of the API, so what a client reads after a restart
is byte for byte what it read before. A few columns (owner, state, request_id) are copied out
of the message for lookups. The store is shared by the gRPC handlers and the runner's lanes, so
every access takes one lock; SQLite in WAL mode keeps those short.
"""

from __future__ import annotations

import errno
import hashlib
import os
import shutil
import sqlite3
import tempfile
import threading
import time
from pathlib import Path

from matopt_api.v1 import matopt_pb2 as pb

from .errors import DiskFull, InvalidArgument, NotFound

_SCHEMA = """
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
"""

# Columns added since the first release, for data dirs made by it.
_MIGRATIONS = {("scenes", "inputs"): "ALTER TABLE scenes ADD COLUMN inputs TEXT"}

CHUNK = 1 << 20
FREE_TO_RESUME = 64 << 20  # after the disk filled up, writes go on once this much is free


class _Connection(sqlite3.Connection):
    """SQLite's "database or disk is full" as DiskFull, which handlers answer with
    RESOURCE_EXHAUSTED and lanes answer by holding their jobs."""

    on_full = staticmethod(lambda: None)

    def execute(self, *args, **kwargs):  # noqa: ANN002, ANN003 - sqlite3's own signature
        try:
            return super().execute(*args, **kwargs)
        except sqlite3.OperationalError as exc:
            if "full" in str(exc):
                self.on_full()
                raise DiskFull() from None
            raise


def disk_full(exc: BaseException) -> bool:
    return isinstance(exc, DiskFull) or (isinstance(exc, OSError)
                                         and exc.errno in (errno.ENOSPC, errno.EDQUOT))


class Store:
    def __init__(self, data_dir: Path) -> None:
        self.root = Path(data_dir)
        self.blob_dir = self.root / "blobs"
        self.blob_dir.mkdir(parents=True, exist_ok=True)
        self._db = sqlite3.connect(self.root / "matoptd.sqlite3", check_same_thread=False,
                                   isolation_level=None, factory=_Connection)
        self._db.on_full = self.note_full
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=NORMAL")
        self._db.executescript(_SCHEMA)
        for (table, column), sql in _MIGRATIONS.items():
            if column not in [r[1] for r in self._db.execute(f"PRAGMA table_info({table})")]:
                self._db.execute(sql)
        self.checkpoint_dir = self.root / "checkpoints"
        self.checkpoint_dir.mkdir(exist_ok=True)
        self._lock = threading.Lock()

    def close(self) -> None:
        with self._lock:
            self._db.close()

    # -- the disk ---------------------------------------------------------------------------

    full_since: float | None = None  # when a write last failed for want of space

    def note_full(self) -> None:
        if self.full_since is None:
            self.full_since = time.monotonic()

    def space_back(self) -> bool:
        """Whether writes can go on: true unless the disk filled up and is still short."""
        if self.full_since is not None and shutil.disk_usage(self.root).free >= FREE_TO_RESUME:
            self.full_since = None
        return self.full_since is None

    def _query(self, sql: str, args: tuple = ()) -> list[tuple]:
        with self._lock:
            return self._db.execute(sql, args).fetchall()

    # -- blobs ------------------------------------------------------------------------------

    def blob_path(self, sha256: str) -> Path:
        if len(sha256) != 64 or any(c not in "0123456789abcdef" for c in sha256):
            raise InvalidArgument(f"'{sha256}' is not a lowercase hex SHA-256 digest")
        return self.blob_dir / sha256[:2] / sha256

    def has_blob(self, sha256: str) -> bool:
        return self.blob_path(sha256).exists()

    def begin_upload(self) -> "Upload":
        return Upload(self)

    def put_blob(self, data: bytes) -> str:
        """Stores bytes; returns the blob's resource name."""
        upload = self.begin_upload()
        upload.write(data)
        return upload.commit().name

    def read_blob(self, name: str) -> bytes:
        return self.blob_file(name).read_bytes()

    def blob_file(self, name: str) -> Path:
        """The file behind ``blobs/{sha256}`` (or a bare digest); NOT_FOUND if absent."""
        sha = name.removeprefix("blobs/")
        path = self.blob_path(sha)
        if not path.exists():
            raise NotFound(f"blob '{name}' not found (upload it first)")
        return path

    # -- scenes -----------------------------------------------------------------------------

    def add_scene(self, owner: str, request_id: str | None, scene: pb.Scene,
                  parameters: pb.ListSceneParametersResponse, inputs: str) -> None:
        """``inputs``: what a worker loads (engine_api.SceneInput as JSON)."""
        with self._lock:
            self._db.execute(
                "INSERT INTO scenes (name, owner, request_id, seq, scene, parameters, inputs) "
                "VALUES (?, ?, ?, (SELECT COALESCE(MAX(seq),0)+1 FROM scenes), ?, ?, ?)",
                (scene.name, owner, request_id or None, scene.SerializeToString(),
                 parameters.SerializeToString(), inputs))

    def scene_inputs(self, name: str) -> str | None:
        rows = self._query("SELECT inputs FROM scenes WHERE name=?", (name,))
        return rows[0][0] if rows else None

    def set_scene_inputs(self, name: str, inputs: str) -> None:
        with self._lock:
            self._db.execute("UPDATE scenes SET inputs=? WHERE name=?", (inputs, name))

    def scene_by_request(self, owner: str, request_id: str) -> pb.Scene | None:
        rows = self._query("SELECT scene FROM scenes WHERE owner=? AND request_id=?",
                           (owner, request_id))
        return pb.Scene.FromString(rows[0][0]) if rows else None

    def get_scene(self, owner: str, name: str) -> pb.Scene:
        rows = self._query("SELECT scene FROM scenes WHERE name=? AND owner=?", (name, owner))
        if not rows:
            raise NotFound(f"scene '{name}' not found")
        return pb.Scene.FromString(rows[0][0])

    def scene_parameters(self, owner: str, name: str) -> pb.ListSceneParametersResponse:
        rows = self._query("SELECT parameters FROM scenes WHERE name=? AND owner=?",
                           (name, owner))
        if not rows:
            raise NotFound(f"scene '{name}' not found")
        return pb.ListSceneParametersResponse.FromString(rows[0][0])

    def list_scenes(self, owner: str, offset: int, limit: int) -> list[pb.Scene]:
        rows = self._query("SELECT scene FROM scenes WHERE owner=? ORDER BY seq LIMIT ? OFFSET ?",
                           (owner, limit, offset))
        return [pb.Scene.FromString(r[0]) for r in rows]

    def delete_scene(self, owner: str, name: str) -> None:
        self.get_scene(owner, name)
        with self._lock:
            self._db.execute("DELETE FROM scenes WHERE name=?", (name,))

    # -- jobs -------------------------------------------------------------------------------

    def add_job(self, job: pb.Job, request_id: str | None) -> None:
        with self._lock:
            self._db.execute(
                "INSERT INTO jobs VALUES (?, ?, ?, (SELECT COALESCE(MAX(seq),0)+1 FROM jobs),"
                " ?, ?, NULL)",
                (job.name, job.owner, request_id or None, job.state, job.SerializeToString()))

    def job_by_request(self, owner: str, request_id: str) -> pb.Job | None:
        rows = self._query("SELECT job FROM jobs WHERE owner=? AND request_id=?",
                           (owner, request_id))
        return pb.Job.FromString(rows[0][0]) if rows else None

    def put_job(self, job: pb.Job) -> None:
        with self._lock:
            self._db.execute("UPDATE jobs SET state=?, job=? WHERE name=?",
                             (job.state, job.SerializeToString(), job.name))

    def get_job(self, name: str, owner: str | None = None) -> pb.Job:
        """A job by name; with ``owner``, another user's job is NOT_FOUND, as if absent."""
        rows = self._query("SELECT job, owner FROM jobs WHERE name=?", (name,))
        if not rows or (owner is not None and rows[0][1] != owner):
            raise NotFound(f"job '{name}' not found")
        return pb.Job.FromString(rows[0][0])

    def list_jobs(self, owner: str | None, offset: int, limit: int,
                  states: tuple[int, ...] = ()) -> list[pb.Job]:
        sql, args = "SELECT job FROM jobs WHERE 1=1", []
        if owner is not None:
            sql += " AND owner=?"
            args.append(owner)
        if states:
            sql += f" AND state IN ({','.join('?' * len(states))})"
            args += states
        sql += " ORDER BY seq LIMIT ? OFFSET ?"
        return [pb.Job.FromString(r[0]) for r in self._query(sql, (*args, limit, offset))]

    def delete_job(self, name: str) -> None:
        with self._lock:
            for table, col in (("jobs", "name"), ("iterations", "job"), ("results", "job")):
                self._db.execute(f"DELETE FROM {table} WHERE {col}=?", (name,))
        self._checkpoint_file(name).unlink(missing_ok=True)

    # -- checkpoints: one file per job, replaced in place ------------------------------------

    def _checkpoint_file(self, name: str) -> Path:
        return self.checkpoint_dir / f"{name.removeprefix('jobs/')}.npz"

    def write_checkpoint(self, name: str, data: bytes) -> None:
        """Atomically: a crash (or a full disk) while writing leaves the previous checkpoint."""
        path = self._checkpoint_file(name)
        tmp = None
        try:
            fd, tmp = tempfile.mkstemp(dir=self.checkpoint_dir, prefix=".write-")
            with os.fdopen(fd, "wb") as f:
                f.write(data)
            os.replace(tmp, path)
        except BaseException as exc:
            if tmp:
                Path(tmp).unlink(missing_ok=True)
            if disk_full(exc):
                self.note_full()
                raise DiskFull() from None
            raise

    def read_checkpoint(self, name: str) -> bytes | None:
        """The job's latest checkpoint (data dirs of the first release kept it as a blob)."""
        try:
            return self._checkpoint_file(name).read_bytes()
        except FileNotFoundError:
            pass
        rows = self._query("SELECT checkpoint FROM jobs WHERE name=?", (name,))
        if rows and rows[0][0]:
            try:
                return self.blob_file(rows[0][0]).read_bytes()
            except NotFound:
                return None
        return None

    def has_checkpoint(self, name: str) -> bool:
        return self.read_checkpoint(name) is not None

    # -- histories and results --------------------------------------------------------------

    def add_iteration(self, job: str, record: pb.IterationRecord) -> None:
        with self._lock:
            self._db.execute("INSERT OR REPLACE INTO iterations VALUES (?, ?, ?)",
                             (job, record.iteration, record.SerializeToString()))

    def history(self, job: str) -> list[pb.IterationRecord]:
        rows = self._query("SELECT record FROM iterations WHERE job=? ORDER BY iteration", (job,))
        return [pb.IterationRecord.FromString(r[0]) for r in rows]

    def truncate_history(self, job: str, keep_below: int) -> None:
        """Forgets iterations from ``keep_below`` on (they will be run again after a resume)."""
        with self._lock:
            self._db.execute("DELETE FROM iterations WHERE job=? AND iteration>=?",
                             (job, keep_below))

    def put_result(self, result: pb.JobResult) -> None:
        with self._lock:
            self._db.execute("INSERT OR REPLACE INTO results VALUES (?, ?, ?)",
                             (result.job, result.which, result.SerializeToString()))

    def result(self, job: str, which: int) -> pb.JobResult | None:
        rows = self._query("SELECT result FROM results WHERE job=? AND which=?", (job, which))
        return pb.JobResult.FromString(rows[0][0]) if rows else None


class Upload:
    """A blob being written: to a temporary file first, renamed into place once its digest
    and size check out, so a broken upload never leaves a blob with the wrong content."""

    def __init__(self, store: Store) -> None:
        self.store = store
        try:
            fd, self.tmp = tempfile.mkstemp(dir=store.blob_dir, prefix=".upload-")
        except OSError as exc:
            if disk_full(exc):
                store.note_full()
                raise DiskFull() from None
            raise
        self.file = os.fdopen(fd, "wb")
        self.digest = hashlib.sha256()
        self.size = 0

    def write(self, chunk: bytes) -> None:
        self.digest.update(chunk)
        self.size += len(chunk)
        try:
            self.file.write(chunk)
        except OSError as exc:
            if disk_full(exc):
                self.store.note_full()
                raise DiskFull() from None
            raise

    def commit(self, sha256: str | None = None, size: int | None = None) -> pb.Blob:
        try:
            self.file.close()
        except OSError as exc:
            self.abort()
            if disk_full(exc):
                self.store.note_full()
                raise DiskFull() from None
            raise
        try:
            got = self.digest.hexdigest()
            if sha256 is not None and got != sha256:
                raise InvalidArgument(f"upload declared sha256 {sha256} but its content hashes "
                                      f"to {got}")
            if size is not None and self.size != size:
                raise InvalidArgument(f"upload of {sha256} declared {size} bytes, got "
                                      f"{self.size}")
            path = self.store.blob_path(got)
            path.parent.mkdir(exist_ok=True)
            os.chmod(self.tmp, 0o444)  # a blob never changes: its name is its content
            os.replace(self.tmp, path)
            return pb.Blob(name=f"blobs/{got}", sha256=got, size_bytes=self.size)
        finally:
            self.abort()

    def abort(self) -> None:
        try:
            self.file.close()
        except OSError:
            pass  # a full disk: the file goes anyway
        if os.path.exists(self.tmp):
            os.unlink(self.tmp)

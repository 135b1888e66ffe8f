"""Everything that must survive a daemon restart: an SQLite database of scenes, jobs, their
iteration histories, results and checkpoints, and content-addressed blobs on disk.

Blobs are kept on disk once per content, and reached per user: the table blob_owners says who
owns which (those who uploaded it, and those the daemon wrote it for: renders, results). A
user's scenes and jobs only ever name blobs the user owns, and a user cannot give up a blob
they still use, so a file nobody owns is used by nobody and leaves the disk.

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
from functools import partial
from pathlib import Path
from typing import Callable, Iterator

from matopt_api.v1 import matopt_pb2 as pb

from matoptd.store import blob_refs
from matoptd.workers.devices import format_size
from matoptd.errors import DiskFull, FailedPrecondition, InvalidArgument, NotFound, ResourceExhausted

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

# Who owns which blob; ``size`` is the blob's, repeated per owner so that usage is one sum.
_OWNERS = ("CREATE TABLE blob_owners (sha256 TEXT NOT NULL, owner TEXT NOT NULL, "
           "size INTEGER NOT NULL, PRIMARY KEY (sha256, owner))",
           "CREATE INDEX blob_owners_owner ON blob_owners(owner)")

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
    def __init__(self, data_dir: Path, quota: int | None = None) -> None:
        """``quota``: the bytes of blobs each user may own (None: no limit)."""
        self.root = Path(data_dir)
        self.quota = quota
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
        if not self._db.execute("SELECT 1 FROM sqlite_master WHERE name='blob_owners'").fetchall():
            self._add_owners()

    def _add_owners(self) -> None:
        """Data dirs from before blobs had owners: each user gets the blobs their scenes and
        jobs name. In one transaction, so a crash halfway leaves no table and the next start
        does it again. Uploads nothing names stay on disk, owned by nobody (an upload of
        the same content makes them someone's again)."""
        self._db.execute("BEGIN")
        try:
            for sql in _OWNERS:
                self._db.execute(sql)
            for owner, _, digests in self._uses():
                for sha in digests:
                    path = self.blob_dir / sha[:2] / sha
                    if _is_digest(sha) and path.exists():
                        self._db.execute("INSERT OR IGNORE INTO blob_owners VALUES (?, ?, ?)",
                                         (sha, owner, path.stat().st_size))
            self._db.execute("COMMIT")
        except BaseException:
            self._db.execute("ROLLBACK")
            raise

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
        if not _is_digest(sha256):
            raise InvalidArgument(f"'{sha256}' is not a lowercase hex SHA-256 digest")
        return self.blob_dir / sha256[:2] / sha256

    def owns(self, owner: str, sha256: str) -> bool:
        """Whether ``owner`` reaches the blob (its file may have been lost: then not)."""
        path = self.blob_path(sha256)
        with self._lock:
            return self._owned(owner, sha256) and path.exists()

    def _owned(self, owner: str, sha256: str) -> bool:
        return bool(self._db.execute("SELECT 1 FROM blob_owners WHERE sha256=? AND owner=?",
                                     (sha256, owner)).fetchall())

    def begin_upload(self, owner: str) -> "Upload":
        return Upload(self, owner)

    def put_blob(self, data: bytes, owner: str) -> str:
        """Stores bytes the daemon made for ``owner``, past their quota if need be (a user's
        renders and results are never lost); returns the blob's resource name."""
        upload = self.begin_upload(owner)
        upload.write(data)
        return upload.commit().name

    def writer(self, owner: str) -> Callable[[bytes], str]:
        return partial(self.put_blob, owner=owner)

    def read_blob(self, name: str, owner: str | None = None) -> bytes:
        return self.blob_file(name, owner).read_bytes()

    def reader(self, owner: str) -> Callable[[str], bytes]:
        """Reads only the blobs ``owner`` reaches; any other is NOT_FOUND."""
        return partial(self.read_blob, owner=owner)

    def blob_file(self, name: str, owner: str | None = None) -> Path:
        """The file behind ``blobs/{sha256}`` (or a bare digest); NOT_FOUND if absent or, with
        ``owner``, not theirs: the same message, so that nobody learns what others hold.
        Without ``owner``: the daemon's own reads (workers' fetches, checkpoints)."""
        sha = name.removeprefix("blobs/")
        path = self.blob_path(sha)
        if not (self.owns(owner, sha) if owner is not None else path.exists()):
            raise _not_found(sha)
        return path

    def _keep(self, tmp: str, sha256: str, size: int, owner: str, within_quota: bool) -> None:
        """Moves a verified upload into place, unless its content is there already, and
        records the owner: under the lock, so that a deletion cannot remove the file between
        the two."""
        path = self.blob_path(sha256)
        with self._lock:
            if within_quota:
                self._check_room(owner, size, sha256)
            if not path.exists():
                path.parent.mkdir(exist_ok=True)
                os.chmod(tmp, 0o444)  # a blob never changes: its name is its content
                os.replace(tmp, path)
            self._db.execute("INSERT OR IGNORE INTO blob_owners VALUES (?, ?, ?)",
                             (sha256, owner, size))

    def usage(self, owner: str) -> int:
        with self._lock:
            return self._usage(owner)

    def _usage(self, owner: str) -> int:
        return self._db.execute("SELECT COALESCE(SUM(size), 0) FROM blob_owners WHERE owner=?",
                                (owner,)).fetchone()[0]

    def check_room(self, owner: str, size: int = 0, sha256: str | None = None) -> None:
        """RESOURCE_EXHAUSTED when uploading ``sha256`` (``size`` bytes) would take ``owner``
        past the quota; without a digest, when the quota is used up: new work is refused then,
        since its results will be stored whatever their size."""
        with self._lock:
            self._check_room(owner, size, sha256)

    def _check_room(self, owner: str, size: int, sha256: str | None) -> None:
        if self.quota is None:
            return
        if sha256 is not None and self._owned(owner, sha256):
            return  # theirs already: it costs nothing more
        used, quota = self._usage(owner), format_size(self.quota)
        room = ("delete blobs you no longer need (ListBlobs lists them with what uses them, "
                "DeleteBlob deletes one)")
        if sha256 is not None and used + size > self.quota:
            raise ResourceExhausted(
                f"blob 'blobs/{sha256}' ({format_size(size)}) would exceed your quota of "
                f"{quota} ({self.quota} bytes): your blobs use {format_size(used)}; {room}")
        if sha256 is None and used >= self.quota:
            raise ResourceExhausted(
                f"your blobs use {format_size(used)} of your quota of {quota} ({self.quota} "
                f"bytes): {room} before starting new work")

    def list_blobs(self, owner: str, offset: int, limit: int) -> list[pb.Blob]:
        rows = self._query("SELECT sha256, size FROM blob_owners WHERE owner=? ORDER BY rowid "
                           "LIMIT ? OFFSET ?", (owner, limit, offset))
        uses = self.blobs_in_use(owner) if rows else {}
        return [pb.Blob(name=f"blobs/{sha}", sha256=sha, size_bytes=size,
                        used_by=uses.get(sha, [])) for sha, size in rows]

    def blobs_in_use(self, owner: str) -> dict[str, list[str]]:
        """Digest -> the names of ``owner``'s scenes and jobs that use it."""
        uses: dict[str, list[str]] = {}
        for _, name, digests in self._uses(owner):
            for sha in digests:
                uses.setdefault(sha, []).append(name)
        return uses

    def _uses(self, owner: str | None = None) -> Iterator[tuple[str, str, set[str]]]:
        """(owner, scene or job name, the digests it names) for every scene and job, or
        ``owner``'s."""
        where, args = (" WHERE owner=?", (owner,)) if owner is not None else ("", ())
        for name, who, scene, inputs in self._query(
                "SELECT name, owner, scene, inputs FROM scenes" + where, args):
            yield who, name, blob_refs.scene_blobs(pb.Scene.FromString(scene), inputs)
        results: dict[str, list[pb.JobResult]] = {}
        for job, result in self._query("SELECT job, result FROM results WHERE job IN "
                                       "(SELECT name FROM jobs" + where + ")", args):
            results.setdefault(job, []).append(pb.JobResult.FromString(result))
        for name, who, job, checkpoint in self._query(
                "SELECT name, owner, job, checkpoint FROM jobs" + where, args):
            yield who, name, blob_refs.job_blobs(pb.Job.FromString(job), results.get(name, ()),
                                                 checkpoint)

    def delete_blob(self, owner: str, name: str) -> None:
        """Gives up ``owner``'s hold on a blob; the file goes once nobody holds it."""
        sha = name.removeprefix("blobs/")
        self.blob_path(sha)  # INVALID_ARGUMENT for a malformed digest
        with self._lock:
            if not self._owned(owner, sha):  # even if its file was lost: the row goes
                raise _not_found(sha)
        using = self.blobs_in_use(owner).get(sha, [])
        if using:
            raise FailedPrecondition(
                f"blob 'blobs/{sha}' is used by {', '.join(using[:5])}"
                f"{f' and {len(using) - 5} more' if len(using) > 5 else ''}: delete "
                f"{'it' if len(using) == 1 else 'them'} first")
        with self._lock:
            self._db.execute("DELETE FROM blob_owners WHERE sha256=? AND owner=?", (sha, owner))
            if not self._db.execute("SELECT 1 FROM blob_owners WHERE sha256=?",
                                    (sha,)).fetchall():
                self.blob_path(sha).unlink(missing_ok=True)

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

    def history(self, job: str, offset: int = 0, limit: int = -1) -> list[pb.IterationRecord]:
        """Records in iteration order; a page of them with ``offset`` and ``limit``."""
        rows = self._query("SELECT record FROM iterations WHERE job=? ORDER BY iteration "
                           "LIMIT ? OFFSET ?", (job, limit, offset))
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


def _is_digest(s: str) -> bool:
    return len(s) == 64 and all(c in "0123456789abcdef" for c in s)


def _not_found(sha256: str) -> NotFound:
    """One message for a blob that does not exist and for another user's."""
    return NotFound(f"blob 'blobs/{sha256}' not found (upload it first)")


class Upload:
    """A blob being written for ``owner``: to a temporary file first, kept once its digest and
    size check out, so a broken upload never leaves a blob with the wrong content. Content
    already on disk is still received and checked (that proves the uploader has it), then
    only its new owner is recorded."""

    def __init__(self, store: Store, owner: str) -> None:
        self.store, self.owner = store, owner
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

    def commit(self, sha256: str | None = None, size: int | None = None,
               within_quota: bool = False) -> pb.Blob:
        """``within_quota``: RESOURCE_EXHAUSTED rather than take the owner past their quota
        (uploads; the daemon's own outputs are kept regardless)."""
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
            self.store._keep(self.tmp, got, self.size, self.owner, within_quota)
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

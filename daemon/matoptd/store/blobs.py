"""Content-addressed blobs: kept on disk once per content (``blobs/ab/abcd...``, read-only),
and reached per user.

The table blob_owners says who owns which: those who uploaded it, and those the daemon wrote it
for (renders, results). A user's scenes and jobs only ever name blobs the user owns, and a user
cannot give up a blob they still use, so a file nobody owns is used by nobody and leaves the
disk. Blobs are named ``blobs/{sha256}`` in the API; a bare digest is taken too.
"""

from __future__ import annotations

import hashlib
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Iterator

from matopt_api.costs import format_size

from ..errors import FailedPrecondition, InvalidArgument, NotFound, ResourceExhausted
from .database import Database
from .disk import Disk

# (owner, scene or job name, the digests it names), for every scene and job (or one user's)
Uses = Callable[[str | None], Iterator[tuple[str, str, set[str]]]]

# ``size`` is the blob's, repeated per owner so that usage is one sum.
OWNERS = ("CREATE TABLE blob_owners (sha256 TEXT NOT NULL, owner TEXT NOT NULL, "
          "size INTEGER NOT NULL, PRIMARY KEY (sha256, owner))",
          "CREATE INDEX blob_owners_owner ON blob_owners(owner)")


@dataclass
class BlobEntry:
    sha256: str
    size: int
    used_by: list[str] = field(default_factory=list)  # the owner's scenes and jobs naming it


def digest(name: str) -> str:
    """The digest of ``blobs/{sha256}`` (or of a bare digest); INVALID_ARGUMENT if malformed."""
    sha = name.removeprefix("blobs/")
    if not is_digest(sha):
        raise InvalidArgument(f"'{sha}' is not a lowercase hex SHA-256 digest")
    return sha


def is_digest(s: str) -> bool:
    return len(s) == 64 and all(c in "0123456789abcdef" for c in s)


def not_found(sha256: str) -> NotFound:
    """One message for a blob that does not exist and for another user's."""
    return NotFound(f"blob 'blobs/{sha256}' not found (upload it first)")


class Blobs:
    def __init__(self, root: Path, db: Database, disk: Disk, quota: int | None, uses: Uses
                 ) -> None:
        """``quota``: the bytes of blobs each user may own (None: no limit); ``uses``: what
        the records name."""
        self.root, self.db, self.disk, self.quota, self._uses = root, db, disk, quota, uses
        self.root.mkdir(parents=True, exist_ok=True)

    def path(self, name: str) -> Path:
        sha = digest(name)
        return self.root / sha[:2] / sha

    def owns(self, owner: str, name: str) -> bool:
        """Whether ``owner`` reaches the blob (its file may have been lost: then not)."""
        path, sha = self.path(name), digest(name)
        with self.db.lock:
            return self._owned(owner, sha) and path.exists()

    def _owned(self, owner: str, sha256: str) -> bool:
        return bool(self.db.connection.execute(
            "SELECT 1 FROM blob_owners WHERE sha256=? AND owner=?", (sha256, owner)).fetchall())

    def file(self, name: str, owner: str | None = None) -> Path:
        """The file of a blob; NOT_FOUND if absent or, with ``owner``, not theirs: the same
        message, so that nobody learns what others hold. Without ``owner``: the daemon's own
        reads (workers' fetches, checkpoints)."""
        path, sha = self.path(name), digest(name)
        if not (self.owns(owner, sha) if owner is not None else path.exists()):
            raise not_found(sha)
        return path

    def read(self, name: str, owner: str | None = None) -> bytes:
        return self.file(name, owner).read_bytes()

    def reader(self, owner: str) -> Callable[[str], bytes]:
        """Reads only the blobs ``owner`` reaches; any other is NOT_FOUND."""
        return lambda name: self.read(name, owner)

    def begin_upload(self, owner: str) -> Upload:
        return Upload(self, owner)

    def put(self, data: bytes, owner: str) -> str:
        """Stores bytes the daemon made for ``owner``, past their quota if need be (a user's
        renders and results are never lost); returns the digest."""
        upload = self.begin_upload(owner)
        upload.write(data)
        return upload.commit()[0]

    def writer(self, owner: str) -> Callable[[bytes], str]:
        return lambda data: self.put(data, owner)

    def _keep(self, tmp: str, sha256: str, size: int, owner: str, within_quota: bool) -> None:
        """Moves a verified upload into place, unless its content is there already, and
        records the owner: under the lock, so that a deletion cannot remove the file between
        the two."""
        path = self.path(sha256)
        with self.db.lock:
            if within_quota:
                self._check_room(owner, size, sha256)
            if not path.exists():
                path.parent.mkdir(exist_ok=True)
                os.chmod(tmp, 0o444)  # a blob never changes: its name is its content
                os.replace(tmp, path)
            self.db.connection.execute("INSERT OR IGNORE INTO blob_owners VALUES (?, ?, ?)",
                                       (sha256, owner, size))

    # -- quota ------------------------------------------------------------------------------

    def usage(self, owner: str) -> int:
        with self.db.lock:
            return self._usage(owner)

    def _usage(self, owner: str) -> int:
        return self.db.connection.execute(
            "SELECT COALESCE(SUM(size), 0) FROM blob_owners WHERE owner=?", (owner,)
        ).fetchone()[0]

    def check_room(self, owner: str, size: int = 0, sha256: str | None = None) -> None:
        """RESOURCE_EXHAUSTED when uploading ``sha256`` (``size`` bytes) would take ``owner``
        past the quota; without a digest, when the quota is used up: new work is refused then,
        since its results will be stored whatever their size."""
        with self.db.lock:
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

    # -- what uses them ---------------------------------------------------------------------

    def list(self, owner: str, offset: int, limit: int) -> list[BlobEntry]:
        rows = self.db.query("SELECT sha256, size FROM blob_owners WHERE owner=? ORDER BY "
                             "rowid LIMIT ? OFFSET ?", (owner, limit, offset))
        uses = self.in_use(owner) if rows else {}
        return [BlobEntry(sha, size, uses.get(sha, [])) for sha, size in rows]

    def in_use(self, owner: str) -> dict[str, list[str]]:
        """Digest -> the names of ``owner``'s scenes and jobs that use it."""
        uses: dict[str, list[str]] = {}
        for _, name, digests in self._uses(owner):
            for sha in digests:
                uses.setdefault(sha, []).append(name)
        return uses

    def delete(self, owner: str, name: str) -> None:
        """Gives up ``owner``'s hold on a blob; the file goes once nobody holds it."""
        sha = digest(name)
        with self.db.lock:
            if not self._owned(owner, sha):  # even if its file was lost: the row goes
                raise not_found(sha)
        using = self.in_use(owner).get(sha, [])
        if using:
            raise FailedPrecondition(
                f"blob 'blobs/{sha}' is used by {', '.join(using[:5])}"
                f"{f' and {len(using) - 5} more' if len(using) > 5 else ''}: delete "
                f"{'it' if len(using) == 1 else 'them'} first")
        with self.db.lock:
            self.db.connection.execute("DELETE FROM blob_owners WHERE sha256=? AND owner=?",
                                       (sha, owner))
            if not self.db.connection.execute("SELECT 1 FROM blob_owners WHERE sha256=?",
                                              (sha,)).fetchall():
                self.path(sha).unlink(missing_ok=True)

    def adopt(self, uses: Iterable[tuple[str, str, set[str]]]) -> None:
        """Data dirs from before blobs had owners: each user gets the blobs their scenes and
        jobs name. In one transaction, so a crash halfway leaves no table and the next start
        does it again. Uploads nothing names stay on disk, owned by nobody (an upload of the
        same content makes them someone's again)."""
        uses = list(uses)  # read before the transaction takes the database's lock
        with self.db.transaction() as db:
            for sql in OWNERS:
                db.execute(sql)
            for owner, _, digests in uses:
                for sha in digests:
                    path = self.root / sha[:2] / sha
                    if is_digest(sha) and path.exists():
                        db.execute("INSERT OR IGNORE INTO blob_owners VALUES (?, ?, ?)",
                                   (sha, owner, path.stat().st_size))


class Upload:
    """A blob being written for ``owner``: to a temporary file first, kept once its digest and
    size check out, so a broken upload never leaves a blob with the wrong content. Content
    already on disk is still received and checked (that proves the uploader has it), then
    only its new owner is recorded."""

    def __init__(self, blobs: Blobs, owner: str) -> None:
        self.blobs, self.owner = blobs, owner
        with blobs.disk.writing():
            fd, self.tmp = tempfile.mkstemp(dir=blobs.root, prefix=".upload-")
        self.file = os.fdopen(fd, "wb")
        self.digest = hashlib.sha256()
        self.size = 0

    def write(self, chunk: bytes) -> None:
        self.digest.update(chunk)
        self.size += len(chunk)
        with self.blobs.disk.writing():
            self.file.write(chunk)

    def commit(self, sha256: str | None = None, size: int | None = None,
               within_quota: bool = False) -> tuple[str, int]:
        """The digest and size once kept. ``within_quota``: RESOURCE_EXHAUSTED rather than
        take the owner past their quota (uploads; the daemon's own outputs are kept
        regardless)."""
        try:
            with self.blobs.disk.writing():
                self.file.close()
            got = self.digest.hexdigest()
            if sha256 is not None and got != sha256:
                raise InvalidArgument(f"upload declared sha256 {sha256} but its content hashes "
                                      f"to {got}")
            if size is not None and self.size != size:
                raise InvalidArgument(f"upload of {sha256} declared {size} bytes, got "
                                      f"{self.size}")
            self.blobs._keep(self.tmp, got, self.size, self.owner, within_quota)
            return got, self.size
        finally:
            self.abort()

    def abort(self) -> None:
        try:
            self.file.close()
        except OSError:
            pass  # a full disk: the file goes anyway
        if os.path.exists(self.tmp):
            os.unlink(self.tmp)

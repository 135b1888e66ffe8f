"""The SQLite database under --data-dir, shared by the records and the blobs' owners: one
connection in WAL mode, every access under one lock (the handlers and the lanes share it; WAL
keeps each access short), and "database or disk is full" as ``DiskFull``."""

from __future__ import annotations

import contextlib
import sqlite3
import threading
from pathlib import Path
from typing import Iterator

from ..errors import DiskFull
from .disk import Disk


class _Connection(sqlite3.Connection):
    disk: Disk | None = None

    def execute(self, *args, **kwargs):  # noqa: ANN002, ANN003 - sqlite3's own signature
        try:
            return super().execute(*args, **kwargs)
        except sqlite3.OperationalError as exc:
            if "full" in str(exc) and self.disk is not None:
                self.disk.note_full()
                raise DiskFull() from None
            raise


class Database:
    def __init__(self, path: Path, disk: Disk) -> None:
        self.connection = sqlite3.connect(path, check_same_thread=False, isolation_level=None,
                                          factory=_Connection)
        self.connection.disk = disk
        self.connection.execute("PRAGMA journal_mode=WAL")
        self.connection.execute("PRAGMA synchronous=NORMAL")
        self.lock = threading.Lock()

    def close(self) -> None:
        with self.lock:
            self.connection.close()

    def query(self, sql: str, args: tuple = ()) -> list[tuple]:
        with self.lock:
            return self.connection.execute(sql, args).fetchall()

    def execute(self, sql: str, args: tuple = ()) -> None:
        with self.lock:
            self.connection.execute(sql, args)

    @contextlib.contextmanager
    def transaction(self) -> Iterator[sqlite3.Connection]:
        """All or nothing, under the lock: a crash or an error halfway leaves no trace."""
        with self.lock:
            self.connection.execute("BEGIN")
            try:
                yield self.connection
                self.connection.execute("COMMIT")
            except BaseException:
                if self.connection.in_transaction:  # SQLite rolls back a full disk's itself
                    self.connection.execute("ROLLBACK")
                raise

    def tables(self) -> set[str]:
        return {r[0] for r in self.query("SELECT name FROM sqlite_master WHERE type='table'")}

    def columns(self, table: str) -> list[str]:
        return [r[1] for r in self.query(f"PRAGMA table_info({table})")]

"""The worker's own side: one engine on one device, answering the daemon's calls.

The daemon starts it (``handle.Worker``) as ``python -m matoptd.workers.serve`` with one end of
a socket pair; a Ray actor (``ray_actor``) runs the same ``serve`` over queues. Its engine
prepares itself (``engine/startup.py``: the variant, the plugins, the kernels warmed), the
worker says it is ready, then answers calls one at a time:

    daemon -> worker   ("call", method, args)       an ``engine_api.Engine`` method (METHODS)
    worker -> daemon   ("fetch", sha256)            needs a blob; answered ("blob", bytes)
                                                    or ("missing", message)
    worker -> daemon   ("ok", result) | ("error", kind, message)
    daemon -> worker   ("exit",)

Mitsuba 3.9's AD must stay on one thread per process, which is why there is one engine per
process and calls never overlap. The worker dies with the daemon: a daemon that is killed
must not leave renderers holding a GPU.
"""

from __future__ import annotations

import argparse
import ctypes
import os
import signal
import sys
import traceback
from multiprocessing.connection import Connection
from pathlib import Path

from .. import engine_api as api

PR_SET_PDEATHSIG = 1


def _die_with_parent(parent: int) -> None:
    """SIGKILL when the daemon's thread that started this process ends (Linux), and a check
    that the daemon did not end before that was set."""
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    except (OSError, AttributeError):
        pass
    if os.getppid() != parent:
        os._exit(1)


def _error_kind(exc: BaseException) -> str:
    if isinstance(exc, api.InvalidInput):
        return "invalid"
    if isinstance(exc, (api.OutOfMemory, MemoryError)) or "out of memory" in str(exc).lower():
        return "memory"
    return "engine" if isinstance(exc, api.EngineError) else "internal"


def _message(exc: BaseException, cache: Path | None = None) -> str:
    """What the daemon is told; the worker's cache, where it lays out bundles, is not named
    (the caller knows only bundle paths, and the daemon's folders are not theirs to see)."""
    text = str(exc) if isinstance(exc, api.EngineError) else f"{type(exc).__name__}: {exc}"
    return text.replace(str(cache), "<worker cache>") if cache is not None else text


def own_directory(cache: Path) -> Path:
    """Moves this process into an empty, read-only directory of its own, before Mitsuba is
    imported: a relative file name a scene gets past every check then finds nothing there,
    rather than the daemon's files in the directory it was started from. Paths given relative
    to that directory (the cache, Dr.Jit's kernel cache) are made absolute first; returns the
    cache's."""
    cache = cache.absolute()
    if os.environ.get("DRJIT_CACHE_DIR"):
        os.environ["DRJIT_CACHE_DIR"] = os.path.abspath(os.environ["DRJIT_CACHE_DIR"])
    empty = cache / "cwd"
    empty.mkdir(parents=True, exist_ok=True)
    empty.chmod(0o555)
    os.chdir(empty)
    return cache



def serve(conn: Connection, cache: Path) -> None:
    """Answers calls until the daemon says exit or goes away. ``conn`` is a socket
    connection, or anything with its ``send`` and ``recv`` (a Ray actor's queues)."""
    from ..engine.service import MitsubaEngine

    def fetch(sha256: str) -> bytes:
        conn.send(("fetch", sha256))
        reply = conn.recv()
        if reply[0] != "blob":
            raise api.InvalidInput(reply[1])
        return reply[1]

    engine = MitsubaEngine(fetch, cache)
    while True:
        try:
            message = conn.recv()
        except (EOFError, OSError):
            return  # the daemon is gone
        if message[0] == "exit":
            return
        _, method, args = message
        try:
            if method not in api.METHODS:
                raise api.EngineError(f"a worker has no call '{method}'")
            result = getattr(engine, method)(*args)
        except Exception as exc:  # noqa: BLE001 - every failure goes back to the caller
            kind = _error_kind(exc)
            if kind == "internal":
                traceback.print_exc(file=sys.stderr)
            conn.send(("error", kind, _message(exc, cache)))
        else:
            conn.send(("ok", result))



def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="matoptd.workers.serve")
    p.add_argument("--fd", type=int, required=True, help="this end of the daemon's socket pair")
    p.add_argument("--parent", type=int, required=True, help="the daemon's pid")
    p.add_argument("--cache", type=Path, required=True, help="this worker's blob cache")
    p.add_argument("--variant", required=True)
    p.add_argument("--cores", default="", help="CPU cores to run on, e.g. 0,1")
    p.add_argument("--threads", type=int, default=0, help="Dr.Jit threads (CPU variants)")
    args = p.parse_args(argv)
    _die_with_parent(args.parent)
    args.cache = own_directory(args.cache)
    # Ctrl-C in the daemon's terminal reaches the whole process group; the daemon decides
    # when its workers stop, after it has checkpointed their jobs. SIGHUP is the daemon's
    # (it reads its tokens again), also when sent to the group.
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, signal.SIG_IGN)
    if args.cores:
        os.sched_setaffinity(0, {int(c) for c in args.cores.split(",")})
    conn = Connection(args.fd)
    try:
        from ..engine.startup import prepare
        info = prepare(args.variant, args.threads)
    except BaseException as exc:  # noqa: BLE001 - reported to the daemon, which says why
        conn.send(("failed", _message(exc)))
        return 1
    conn.send(("ready", info))
    serve(conn, args.cache)
    return 0


if __name__ == "__main__":
    sys.exit(main())

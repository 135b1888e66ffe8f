"""A worker as a Ray actor: the engine of ``serve.py`` on a machine of a Ray cluster.

The actor runs the same preparation and ``serve`` as a worker process, on one thread of its
own (Mitsuba's AD stays on one thread), and speaks the same messages; only the pipe differs.
Instead of a socket, two queues: the daemon ``push``es its messages in and ``take``s the
worker's out, each a Ray call. Blobs the daemon sends and results the worker returns travel
through Ray's object store, so no file system is shared with the daemon.

This module runs on the cluster's machines; each needs ``matopt-mitsuba[daemon,ray]`` installed.
"""

from __future__ import annotations

import os
import queue
import tempfile
import threading
from pathlib import Path

import ray

from . import serve
from .devices import find_libllvm


class QueueConnection:
    """The engine's end of the pipe: what ``serve.serve`` needs of a socket connection."""

    def __init__(self, inbox: queue.Queue, outbox: queue.Queue) -> None:
        self.inbox, self.outbox = inbox, outbox

    def send(self, message: tuple) -> None:
        self.outbox.put(message)

    def recv(self) -> tuple:
        return self.inbox.get()


def resident_memory() -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    return 0


@ray.remote(max_restarts=0, max_concurrency=4)
class EngineActor:
    """One engine. Its calls (``ready``, ``push``, ``take``) run on Ray's threads of the
    actor; the engine runs on its own thread."""

    def __init__(self, variant: str, threads: int, name: str) -> None:
        # Dr.Jit reads these once, at import: this machine's libLLVM and a kernel cache
        # that outlives the actor, so a restarted worker starts warm.
        base = Path(tempfile.gettempdir()) / f"matoptd-ray-{os.getuid()}"
        os.environ.setdefault("DRJIT_CACHE_DIR", str(base / "kernel-cache"))
        llvm = find_libllvm()
        if llvm:
            os.environ.setdefault("DRJIT_LIBLLVM_PATH", llvm)
        self.inbox: queue.Queue = queue.Queue()
        self.outbox: queue.Queue = queue.Queue()
        cache = serve.own_directory(base / name.replace("/", "-") / "worker-cache")
        node = ray.get_runtime_context().get_node_id()
        threading.Thread(target=self._run, args=(variant, threads, cache, node),
                         name="matoptd-engine", daemon=True).start()

    def _run(self, variant: str, threads: int, cache: Path, node: str) -> None:
        try:
            from ..engine.startup import prepare
            info = prepare(variant, threads)
        except BaseException as exc:  # noqa: BLE001 - reported to the daemon, which says why
            self.outbox.put(("failed", f"{type(exc).__name__}: {exc}"))
            return
        self.outbox.put(("ready", {**info, "node": node}))
        serve.serve(QueueConnection(self.inbox, self.outbox), cache)

    def push(self, *message) -> None:
        # Top-level object references among the arguments arrive resolved (blobs as bytes).
        self.inbox.put(message)

    def take(self, timeout: float) -> tuple[tuple | None, int]:
        """The worker's next message (None if none came within ``timeout`` seconds) and the
        process's resident memory, which the daemon holds against the worker's limit."""
        try:
            message = self.outbox.get(timeout=timeout)
        except queue.Empty:
            message = None
        return message, resident_memory()

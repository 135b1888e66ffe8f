"""The daemon's renderer workers in words, for ``matopt info`` and the Qt status bar.

Pure functions of ``pb.Worker`` messages (no click, no Qt), so the CLI and the window say the
same thing about a worker and tests can check the wording without a daemon.
"""

from __future__ import annotations

from collections import Counter
from typing import Iterable, Sequence

from matopt_api.v1 import matopt_pb2 as pb

# The word a user reads for each state; also the order the summary lists the states in
# (what is working first, then what needs attention).
STATE_WORDS: dict[int, str] = {
    pb.WORKER_STATE_BUSY: "busy",
    pb.WORKER_STATE_IDLE: "idle",
    pb.WORKER_STATE_STARTING: "starting",
    pb.WORKER_STATE_RESTARTING: "restarting",
    pb.WORKER_STATE_FAILED: "failed",
    pb.WORKER_STATE_UNSPECIFIED: "unknown",
}

# States that mean jobs on the worker are not being served as they should.
TROUBLE_STATES = frozenset({pb.WORKER_STATE_RESTARTING, pb.WORKER_STATE_FAILED})


def state_word(state: int) -> str:
    """``busy``, ``idle``, ...; a state added to the API later reads as ``unknown``."""
    return STATE_WORDS.get(state, "unknown")


def memory_size(n: int) -> str:
    """Resident memory as people read it: 312 MiB, 8.0 GiB (renderers use MiBs to GiBs)."""
    if n >= 1024**3:
        return f"{n / 1024**3:.1f} GiB"
    if n >= 1024**2:
        return f"{n / 1024**2:.0f} MiB"
    if n >= 1024:
        return f"{n / 1024:.0f} KiB"
    return f"{n} B"


def memory_text(worker: pb.Worker) -> str:
    """``312 MiB of 8.0 GiB``: how close the worker is to the limit that would stop it.

    Empty while no process runs (a pid of 0), where a figure would be stale.
    """
    if worker.pid <= 0:
        return ""
    limit = memory_size(worker.memory_limit_bytes) if worker.memory_limit_bytes > 0 else ""
    if worker.memory_bytes <= 0:
        return f"limit {limit}" if limit else ""
    used = memory_size(worker.memory_bytes)
    return f"{used} of {limit}" if limit else used


def jobs_text(worker: pb.Worker) -> str:
    """``2 jobs (yours: jobs/ab12)``: all users' jobs are counted, only the caller's named.

    The daemon names only the caller's own jobs (``jobs``), so other users' job names never
    appear here; a count below the named ones (an inconsistent reply) is raised to them.
    """
    count = max(worker.job_count, len(worker.jobs))
    if count == 0:
        return "no jobs"
    text = f"{count} job" + ("" if count == 1 else "s")
    if worker.jobs:
        text += f" (yours: {', '.join(worker.jobs)})"
    return text


def process_text(worker: pb.Worker) -> str:
    """``pid 1234 @ gpu-box``, ``pid 1234 @ gpu-box, node 3fa2b9c1`` for a worker on a Ray
    cluster, or ``no process`` between a crash and its restart."""
    where = f" @ {worker.host}" if worker.host else ""
    if worker.node:
        where += f"{',' if where else ''} node {worker.node[:8]}"
    return f"pid {worker.pid}{where}" if worker.pid > 0 else f"no process{where}"


def device_text(worker: pb.Worker, server_variant: str = "") -> str:
    """The worker's device; its variant only when it differs from the server's (mixed CUDA
    and CPU workers), and its thread count when the device string does not already say it."""
    text = worker.device or "unknown device"
    if worker.threads > 0 and "thread" not in text:
        text += f", {worker.threads} threads"
    if worker.variant and worker.variant != server_variant:
        text += f" ({worker.variant})"
    return text


def restarts_text(worker: pb.Worker) -> str:
    """``restarts 1 (last: killed by SIGKILL during jobs/ab12)``; empty for a worker that
    never stopped. A failed worker's reason is shown even without restarts: it is the only
    clue why it could not start."""
    last = f"last: {worker.last_exit}" if worker.last_exit else ""
    if worker.restarts > 0:
        return f"restarts {worker.restarts}" + (f" ({last})" if last else "")
    return f"({last})" if last else ""


def worker_cells(worker: pb.Worker, server_variant: str = "") -> list[str]:
    """One worker as columns: name, state, device, process, memory, jobs, restarts."""
    return [worker.name, state_word(worker.state), device_text(worker, server_variant),
            process_text(worker), memory_text(worker), jobs_text(worker),
            restarts_text(worker)]


def align(rows: Sequence[Sequence[str]], gap: str = "  ") -> list[str]:
    """Rows of cells as lines with left-aligned columns; trailing blanks stripped."""
    if not rows:
        return []
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    return [gap.join(c.ljust(w) for c, w in zip(row, widths)).rstrip() for row in rows]


def worker_lines(workers: Iterable[pb.Worker], server_variant: str = "") -> list[str]:
    """One aligned line per worker, as ``matopt info`` prints them."""
    return align([worker_cells(w, server_variant) for w in workers])


def summary(workers: Sequence[pb.Worker]) -> str:
    """``2 workers: 1 busy, 1 idle``: the count by state, states in :data:`STATE_WORDS`'s
    order; ``no workers`` when the daemon lists none."""
    if not workers:
        return "no workers"
    counts = Counter(state_word(w.state) for w in workers)
    parts = [f"{counts[word]} {word}" for word in dict.fromkeys(STATE_WORDS.values())
             if counts[word]]
    noun = "worker" if len(workers) == 1 else "workers"
    return f"{len(workers)} {noun}: " + ", ".join(parts)


def in_trouble(workers: Iterable[pb.Worker]) -> bool:
    """Whether any worker is restarting or failed (the window then colours its summary)."""
    return any(w.state in TROUBLE_STATES for w in workers)

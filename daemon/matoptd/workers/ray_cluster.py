"""Workers on a Ray cluster (``matoptd --ray ADDRESS``): the daemon is the Ray driver.

Each worker is an ``EngineActor`` (``ray_actor.py``) pinned to one node: one per GPU a node
offers, or ``--workers`` CPU actors per node on a cluster without GPUs. ``RayWorker`` is the
daemon's handle on one; it is a ``handle.Worker`` whose pipe is two Ray calls, so the lanes,
the scheduler and the store treat it like a local process. ``ClusterWatch`` follows the
cluster: a node that joins adds workers, a node that leaves retires its workers (their jobs go
back to the queue and continue from their checkpoints elsewhere).

The store stays on the daemon's machine: actors fetch inputs by hash and return checkpoints
and results as call results, both through Ray's object store.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable

import ray
from ray.exceptions import RayError
from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

from .devices import NUMPY_ENVIRONMENT, Placement, total_memory
from .handle import START_TIMEOUT_S, Worker, WorkerLost

log = logging.getLogger("matoptd.ray")

WATCH_PERIOD_S = 2.0  # how often the cluster's nodes are looked at


def connect(address: str) -> None:
    """``ray.init`` on ``address`` ("auto", "ray://head:10001", "HOST:PORT"), or a private Ray
    instance on this machine for "local"."""
    kwargs: dict[str, Any] = {"namespace": "matoptd", "log_to_driver": True,
                              "configure_logging": False}
    if address == "local":  # a new instance, even when another runs on this machine
        kwargs["include_dashboard"] = False
    ray.init(address=address, **kwargs)


@dataclass(frozen=True)
class Slot:
    """Where one Ray worker runs: a node, and a GPU of it (``gpu``) or a share of its CPUs."""

    name: str       # "workers/<node id prefix>-<index>"
    node: str       # Ray node id
    address: str    # the node's IP
    gpu: bool
    threads: int
    memory: int     # bytes the worker may hold


def has_gpu(nodes: list[dict]) -> bool:
    return any(n.get("Alive") and n["Resources"].get("GPU", 0) >= 1 for n in nodes)


def slots(nodes: list[dict], cpu_workers: int | None,
          memory_limit: int | None = None) -> list[Slot]:
    """The workers a cluster's live nodes (``ray.nodes()``) offer: one per GPU of each
    (``cpu_workers`` None), or ``cpu_workers`` per node. A node's CPUs and memory are shared
    evenly by its workers."""
    alive = [n for n in nodes if n.get("Alive")]
    gpu = cpu_workers is None
    out = []
    for n in sorted(alive, key=lambda n: n["NodeID"]):
        res = n["Resources"]
        count = int(res.get("GPU", 0)) if gpu else cpu_workers
        cpus = int(res.get("CPU", 1))
        memory = memory_limit or int(0.8 * res.get("memory", total_memory()) / max(count, 1))
        for i in range(count):
            out.append(Slot(f"workers/{n['NodeID'][:8]}-{i}", n["NodeID"],
                            n.get("NodeManagerAddress", ""), gpu,
                            max(1, cpus // max(count, 1)), memory))
    return out


def node_alive(node: str) -> bool:
    try:
        return any(n["NodeID"] == node and n.get("Alive") for n in ray.nodes())
    except RayError:
        return False


class ActorConnection:
    """The daemon's end of the pipe to an ``EngineActor``: ``send``, ``poll`` and ``recv`` as
    a socket connection has them. A dead actor reads as a closed pipe (EOFError)."""

    def __init__(self, actor: Any) -> None:
        self.actor = actor
        self.rss = 0
        self.error = ""  # how the pipe broke, in Ray's words
        self._next: tuple | None = None

    def send(self, message: tuple) -> None:
        # Blobs go into the object store once; the actor receives them as bytes.
        args = [ray.put(x) if isinstance(x, bytes) else x for x in message]
        self._get(self.actor.push.remote(*args))

    def poll(self, timeout: float) -> bool:
        if self._next is None:
            self._next, self.rss = self._get(self.actor.take.remote(timeout))
        return self._next is not None

    def recv(self) -> tuple:
        while not self.poll(1.0):
            pass
        message, self._next = self._next, None
        return message

    def close(self) -> None:
        self._next = None

    def _get(self, ref: Any) -> Any:
        try:
            return ray.get(ref)
        except RayError as exc:
            text = str(exc).strip()
            self.error = text.splitlines()[0] if text else type(exc).__name__
            raise EOFError(self.error) from None


@dataclass
class RayWorker(Worker):
    """A worker hosted by an ``EngineActor`` on ``node``."""

    gpu: bool = False
    _actor: Any = None

    @property
    def pid(self) -> int:
        return self.info.get("pid", 0) if self._conn is not None else 0

    def start(self, timeout: float = START_TIMEOUT_S) -> None:
        from .ray_actor import EngineActor

        self._stopping = self._stop_cause = ""
        if not node_alive(self.node):
            raise self._left()
        actor = EngineActor.options(
            num_gpus=1 if self.gpu else 0, num_cpus=0 if self.gpu else self.placement.threads,
            scheduling_strategy=NodeAffinitySchedulingStrategy(self.node, soft=False),
            runtime_env={"env_vars": NUMPY_ENVIRONMENT},
        ).remote(self.variant, self.placement.threads, self.name)
        with self._lock:
            self._actor, self._conn = actor, ActorConnection(actor)
        began = time.monotonic()
        while True:
            try:
                message = self._first(1.0)
            except EOFError:
                raise self._lost() from None
            if message is not None:
                break
            if not node_alive(self.node):
                self.kill("could not start: its node left the cluster", "gone")
                raise self._left()
            if time.monotonic() - began > timeout:
                self.kill(f"did not start within {timeout:g} s (is a {'GPU' if self.gpu else 'CPU'}"
                          " free on its node?)", "hung")
                raise self._lost()
        if message[0] != "ready":
            self._kill_actor()
            self.state = "failed"
            self.last_exit = f"could not start: {message[1]}"
            raise WorkerLost(self.last_exit, "died")
        self.info = message[1]
        self.state = "idle"
        log.info("%s ready in %.1f s: %s on %s, node %s (%s)", self.name, self.info["seconds"],
                 self.info["variant"], self.info["device"], self.node[:8],
                 self.info.get("host", ""))

    def _first(self, timeout: float) -> tuple | None:
        conn = self._conn
        return conn.recv() if conn.poll(timeout) else None

    def stop(self) -> None:
        with self._lock:
            conn = self._conn
        if conn is None:
            return
        self._stopping, self._stop_cause = "was stopped with the daemon", "stopped"
        try:
            conn.send(("exit",))
        except EOFError:
            pass
        self._kill_actor()

    def kill(self, reason: str, cause: str) -> None:
        with self._lock:
            if self._actor is None or self._stopping:
                return
            self._stopping, self._stop_cause = reason, cause
        log.warning("%s (node %s) stopped: %s", self.name, self.node[:8], reason)
        self._kill_actor()

    def _kill_actor(self) -> None:
        if self._actor is not None:
            try:
                ray.kill(self._actor, no_restart=True)
            except RayError:
                pass

    def memory(self) -> int:
        conn = self._conn
        return conn.rss if conn is not None else 0

    def _exited(self) -> bool:
        return False  # a dead actor shows as a broken pipe on the next poll

    def _lost(self) -> WorkerLost:
        if self._stopping:
            reason, cause = self._stopping, self._stop_cause
        elif not node_alive(self.node):
            lost = self._left()
            reason, cause = lost.reason, lost.cause
        else:
            error = self._conn.error if self._conn is not None else ""
            reason, cause = f"died ({error or 'its Ray actor ended'})", "died"
        self._kill_actor()
        self.state, self.last_exit = "restarting", reason
        with self._lock:
            self._conn, self._actor = None, None
        return WorkerLost(reason, cause)

    def _left(self) -> WorkerLost:
        self.gone = True
        where = self.info.get("host") or self.node[:8]
        self.last_exit = f"left with its node ({where}), which is no longer in the cluster"
        return WorkerLost(self.last_exit, "gone")


class ClusterWatch:
    """Keeps the workers in step with the cluster: ``add`` for each worker a node brings,
    ``retire`` for each whose node left. Runs on a thread of its own."""

    def __init__(self, make: Callable[[Slot], Worker], add: Callable[[Worker], None],
                 retire: Callable[[str, str], None], known: Callable[[], dict[str, Worker]],
                 cpu_workers: int | None, memory_limit: int | None) -> None:
        self._make, self._add, self._retire, self._known = make, add, retire, known
        self._cpu_workers, self._memory_limit = cpu_workers, memory_limit
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="matoptd-cluster", daemon=True)

    def initial(self) -> list[Worker]:
        """The workers of the cluster as it is now. Whether they are GPU or CPU workers is
        decided here, once: GPU workers unless CPU workers were asked for or the cluster has
        no GPU now. A GPU cluster that loses its last GPU machine then waits for one, rather
        than rendering on the head's CPUs."""
        nodes = ray.nodes()
        if self._cpu_workers is None and not has_gpu(nodes):
            log.warning("the Ray cluster offers no GPU: one CPU worker per machine "
                        "(--workers N for more)")
            self._cpu_workers = 1
        return [self._make(s) for s in slots(nodes, self._cpu_workers, self._memory_limit)]

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()
        ray.shutdown()

    def _loop(self) -> None:
        while not self._stop.wait(WATCH_PERIOD_S):
            try:
                nodes = ray.nodes()
            except RayError as exc:
                log.error("cannot see the Ray cluster: %s", exc)
                continue
            self.reconcile(nodes)

    def reconcile(self, nodes: list[dict]) -> None:
        wanted = {s.name: s for s in slots(nodes, self._cpu_workers, self._memory_limit)}
        known = self._known()
        for name, slot in wanted.items():
            if name not in known:
                log.info("node %s (%s) joined: adding %s", slot.node[:8], slot.address, name)
                self._add(self._make(slot))
        alive = {n["NodeID"] for n in nodes if n.get("Alive")}
        for name, w in known.items():
            if w.node and w.node not in alive and not w.gone:
                self._retire(name, f"its node ({w.info.get('host') or w.node[:8]}) left the "
                             "cluster")


def make_worker(slot: Slot, variant: str | None, fetch: Callable[[str], bytes],
                data_dir) -> RayWorker:
    return RayWorker(slot.name, Placement(None, (), slot.threads),
                     variant or ("cuda_ad_rgb" if slot.gpu else "llvm_ad_rgb"), data_dir,
                     slot.memory, fetch, node=slot.node, gpu=slot.gpu)


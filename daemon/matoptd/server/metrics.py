"""Prometheus metrics (``matoptd --metrics-port``): what an operator watches, served over
HTTP at /metrics by prometheus_client, apart from the gRPC API.

Two kinds. Events are counted as they happen: iterations per worker and the wait of each
job that leaves the queue (the scheduler's ``Observer``), and each RPC's latency
(``interceptors.Latency``). States are read when a scrape asks (``_Now``): jobs by phase,
each user's active jobs, each worker's memory, limit, restarts and state. So a scrape costs
one SQL count and a walk over the workers and active jobs, and nothing is kept twice.

Metrics never break a job or a call: a failure to count or collect is logged (once per
kind, so that a broken metric does not flood the log) and the metric is left out.
"""

from __future__ import annotations

import collections
import functools
import logging
from typing import Any, Callable, Iterator

from prometheus_client import (CollectorRegistry, Counter, Histogram, disable_created_metrics,
                               start_http_server)
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.process_collector import ProcessCollector

from ..records import Phase
from ..scheduling.lanes import Lanes
from ..scheduling.scheduler import Job
from ..store.store import Store

log = logging.getLogger("matoptd.metrics")

# A job's wait in the queue: from seconds (an idle worker) to hours (a busy day).
QUEUE_BUCKETS = (0.1, 0.5, 1, 2.5, 5, 10, 30, 60, 120, 300, 600, 1800, 3600, 4 * 3600)
# An RPC: a status call takes a millisecond; an upload or a scene load, seconds.
RPC_BUCKETS = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30, 60)

_failed: set[str] = set()  # the kinds whose failure was logged


def safely(fn: Callable[..., Any]) -> Callable[..., Any]:
    """``fn`` that logs its first failure instead of raising (None then)."""
    @functools.wraps(fn)
    def guarded(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except Exception:  # noqa: BLE001 - a metric must never cost a job or a call
            if fn.__qualname__ not in _failed:
                _failed.add(fn.__qualname__)
                log.exception("metrics: %s failed (left out from now on until it works; "
                              "logged once)", fn.__qualname__)
            return None
    return guarded


class Metrics:
    """The daemon's metrics in a registry of their own (none of prometheus_client's global
    one), the scheduler's observer and the latency interceptor's sink."""

    def __init__(self, store: Store) -> None:
        disable_created_metrics()  # *_created series: noise for a daemon's counters
        self.registry = CollectorRegistry()
        self.iterations = Counter(
            "matoptd_worker_iterations", "Iterations run, by worker; rate() is iterations/s",
            ["worker"], registry=self.registry)
        self.queue_wait = Histogram(
            "matoptd_queue_wait_seconds", "Seconds a job waited QUEUED before a worker "
            "loaded it (new, resumed, or sent back by a lost worker)",
            buckets=QUEUE_BUCKETS, registry=self.registry)
        self.rpc_latency = Histogram(
            "matoptd_rpc_duration_seconds", "Seconds from a call's start to its answer (a "
            "stream: to its end), by method and status code",
            ["method", "code"], buckets=RPC_BUCKETS, registry=self.registry)
        self.now = _Now(store)
        self.registry.register(self.now)
        ProcessCollector(registry=self.registry)  # the daemon's own CPU and memory
        self._server = None

    def watch(self, lanes: Lanes) -> None:
        """The workers and the scheduler, once started: their metrics come from then on."""
        self.now.lanes = lanes
        lanes.state.scheduler.observer = self

    @safely
    def started(self, job: Job, waited: float) -> None:
        self.queue_wait.observe(max(0.0, waited))

    @safely
    def stepped(self, worker: str, iterations: int) -> None:
        self.iterations.labels(worker).inc(iterations)

    @safely
    def rpc(self, method: str, code: str, seconds: float) -> None:
        self.rpc_latency.labels(method, code).observe(seconds)

    def serve(self, address: str) -> tuple[str, int]:
        """Serves /metrics on ``address`` ("[HOST:]PORT"); returns where. ValueError for an
        address that is not one, OSError when it cannot be bound."""
        host, port = parse_address(address)
        self._server, _ = start_http_server(port, host, registry=self.registry)
        return host, self._server.server_port

    def stop(self) -> None:
        if self._server is not None:
            self._server.shutdown()


def parse_address(address: str, default_host: str = "127.0.0.1") -> tuple[str, int]:
    """"9464" -> (default_host, 9464); "0.0.0.0:9464", "[::1]:9464" as given."""
    host, _, port = address.rpartition(":")
    if not port.isdigit() or int(port) > 65535:
        raise ValueError(f"'{address}' is not PORT or HOST:PORT")
    return host.strip("[]") or default_host, int(port)


class _Now:
    """The states, read at each scrape; each family on its own, so that one that fails is
    left out and the others still come."""

    def __init__(self, store: Store) -> None:
        self.store = store
        self.lanes: Lanes | None = None  # once the workers are started

    def collect(self) -> Iterator[Metric]:
        yield from self._jobs() or ()
        if self.lanes is not None:
            yield from self._users() or ()
            yield from self._workers() or ()

    @safely
    def _jobs(self) -> list[Metric]:
        jobs = GaugeMetricFamily("matoptd_jobs", "Jobs by phase, every user's",
                                 labels=["phase"])
        for phase, count in self.store.count_by_phase().items():
            jobs.add_metric([phase.value], count)
        return [jobs]

    @safely
    def _users(self) -> list[Metric]:
        state = self.lanes.state
        with state.lock:
            active = collections.Counter((j.user, j.phase.value)
                                         for j in state.scheduler.jobs.values())
        users = GaugeMetricFamily("matoptd_user_jobs", "Each user's jobs the scheduler "
                                  "holds (queued, running, and those on their way to "
                                  "paused or ended), by phase", labels=["user", "phase"])
        for user in {u for u, _ in active}:
            for phase in (Phase.QUEUED, Phase.RUNNING):  # always both, 0 when none
                users.add_metric([user, phase.value], active.pop((user, phase.value), 0))
        for (user, phase), count in active.items():
            users.add_metric([user, phase], count)
        return [users]

    @safely
    def _workers(self) -> list[Metric]:
        memory = GaugeMetricFamily("matoptd_worker_memory_bytes", "Resident memory of each "
                                   "worker process", labels=["worker"])
        limit = GaugeMetricFamily("matoptd_worker_memory_limit_bytes", "Resident memory a "
                                  "worker may use before it is stopped (--worker-memory)",
                                  labels=["worker"])
        restarts = CounterMetricFamily("matoptd_worker_restarts", "Times each worker was "
                                       "restarted (it died, hung, or passed its memory limit)",
                                       labels=["worker"])
        states = GaugeMetricFamily("matoptd_worker_state", "1 for each worker's state "
                                   "(starting, idle, busy, restarting, failed, ...)",
                                   labels=["worker", "state"])
        for w in list(self.lanes.state.workers.values()):  # replaced whole, never changed
            memory.add_metric([w.name], w.memory())
            limit.add_metric([w.name], w.memory_limit or 0)
            restarts.add_metric([w.name], w.restarts)
            states.add_metric([w.name, w.state], 1)
        return [memory, limit, restarts, states]

"""``matoptd``: start the daemon. Its options, their environment variables and its config
file are ``options.py``'s (``matoptd --help`` lists them).

This process serves the API and never imports Mitsuba or Dr.Jit: it starts one renderer
worker process per CUDA device that works (or CPU workers), supervises them and restarts them.
With ``--ray`` the workers are Ray actors on the machines of a Ray cluster instead
(``workers/ray_cluster.py``).
"""

from __future__ import annotations

import argparse
import asyncio
import ipaddress
import logging
import signal

import grpc
from grpc_health.v1 import health_pb2

from matopt_api.costs import format_size

from . import __version__, logs
from .options import LIMITS, SERVER_NICE, SERVER_NICE_SHARED, SERVER_TURN_S, parse_args
from .scheduling.control import JobControl
from .scheduling.lanes import Lanes
from .scheduling.recovery import Recovery
from .scheduling.scheduler import Scheduler
from .scheduling.state import State
from .server import admission, app
from .server.backend import Backend
from .server.metrics import Metrics
from .server.auth import Authenticator
from .store.store import Store
from .workers import devices, sizing
from .workers.handle import Handle, Worker

log = logging.getLogger("matoptd")

def server_nice(asked: int | None, renders_beside: bool) -> int:
    """``--server-nice``, or by default the lowest priority where CPU workers render on the
    server's own cores. There every status call's CPU (0.5 ms of gRPC's own per GetJob) comes
    out of the job's: 200 GetJob/s and 16 watch streams slowed a job on 2 cores by 13-19% at
    nice 10, the server's share capped but still taken, and by 2% at 19, where the calls
    wait for the render instead (bench/control_plane.py). Beside a GPU's workers, whose
    render is on the device, 10 keeps the calls prompt."""
    if asked is not None:
        return int(asked)
    return SERVER_NICE_SHARED if renders_beside else SERVER_NICE


def is_loopback(host: str) -> bool:
    host = host.strip("[]")
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


async def serve(args: argparse.Namespace) -> None:
    host, _, port = args.listen.rpartition(":")
    if not host or not port.isdigit():
        raise SystemExit(f"matoptd: --listen must be HOST:PORT, got '{args.listen}'")
    auth = Authenticator(None)
    if args.tokens:
        try:
            auth = Authenticator.from_file(args.tokens)
        except (OSError, ValueError) as exc:
            raise SystemExit(f"matoptd: cannot use tokens file: {exc}")
    elif not is_loopback(host):
        raise SystemExit(f"matoptd: refusing to listen on {host} without --tokens: anyone "
                         "who can reach it would be the local user")
    # From here on, while the workers start too: SIGHUP's default would end the daemon.
    asyncio.get_running_loop().add_signal_handler(signal.SIGHUP, auth.reload)
    if bool(args.tls_cert) != bool(args.tls_key):
        raise SystemExit("matoptd: --tls-cert and --tls-key go together")

    quota = None
    if args.quota:
        try:
            quota = devices.parse_size(args.quota)
        except ValueError as exc:
            raise SystemExit(f"matoptd: --quota: {exc}")
        if quota < 1:
            raise SystemExit(f"matoptd: --quota must be at least 1 byte, got '{args.quota}'")

    try:
        limits = admission.Limits(**{name: getattr(args, name) for name in LIMITS})
    except ValueError as exc:
        raise SystemExit(f"matoptd: {exc}")
    args.data_dir.mkdir(parents=True, exist_ok=True)
    try:
        store = Store(args.data_dir, quota)
    except RuntimeError as exc:  # a data dir made by a newer matoptd
        raise SystemExit(f"matoptd: --data-dir {args.data_dir}: {exc}")
    metrics = start_metrics(args.metrics_port, store) if args.metrics_port else None
    cluster = None
    if args.ray:
        lanes, cluster = await asyncio.to_thread(start_ray_workers, args, store)
    else:
        lanes = await asyncio.to_thread(start_workers, args, store)

    if metrics is not None:
        metrics.watch(lanes)
    beside = cluster is None and args.worker_cores is None and any(
        w.placement.cuda is None for w in lanes.state.workers.values())
    nice = server_nice(args.server_nice, beside)
    if nice > 0:
        devices.lower_priority(nice, lanes.thread_ids())
        log.info("server threads %d nice levels below the workers", nice)
        lanes.state.server_turn = SERVER_TURN_S if beside else 0.0
    backend = Backend(store, lanes, JobControl(lanes.state, lanes.recovery),
                          lanes.state.events, limits)
    server, health_servicer, names = app.build(backend, auth,
                                               metrics.rpc if metrics is not None else None)
    if args.tls_cert:
        creds = grpc.ssl_server_credentials([(args.tls_key.read_bytes(),
                                              args.tls_cert.read_bytes())])
        bound = server.add_secure_port(args.listen, creds)
    else:
        bound = server.add_insecure_port(args.listen)
    await server.start()
    for name in names:
        await health_servicer.set(name, health_pb2.HealthCheckResponse.SERVING)
    if args.port_file:
        tmp = args.port_file.with_suffix(".tmp")
        tmp.write_text(str(bound))
        tmp.replace(args.port_file)
    log.info("matoptd %s serving on %s:%d (%d worker(s), %s, %s)", __version__, host, bound,
             sum(w.state == "idle" for w in lanes.state.workers.values()),
             "TLS" if args.tls_cert else "plaintext",
             f"{len(auth.users)} user(s)" if args.tokens else "local user only")
    if quota is not None:
        log.info("blob quota: %s per user", format_size(quota))

    stop = asyncio.Event()
    loop = asyncio.get_running_loop()

    def on_signal() -> None:
        lanes.begin_stop()
        stop.set()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, on_signal)
    health_task = asyncio.create_task(app.report_health(health_servicer, names, lanes, stop))
    await stop.wait()
    await health_task
    log.info("shutting down: finishing the current iteration")
    await health_servicer.enter_graceful_shutdown()
    # Side by side: open calls (a watch stream never ends by itself) get their grace while
    # the workers finish their iterations, so a shutdown takes the longer of the two, not both.
    await asyncio.gather(server.stop(grace=5), asyncio.to_thread(lanes.stop))
    if cluster is not None:
        cluster.stop()
    if metrics is not None:
        metrics.stop()
    store.close()
    log.info("stopped")



def start_metrics(address: str, store: Store) -> Metrics:
    """/metrics served before the workers start, so that a port in use ends the daemon at
    once rather than after a minute of starting workers."""
    metrics = Metrics(store)
    try:
        host, port = metrics.serve(address)
    except (ValueError, OSError) as exc:
        raise SystemExit(f"matoptd: --metrics-port {address}: {exc}")
    log.info("metrics on http://%s:%d/metrics", host if ":" not in host else f"[{host}]", port)
    if not is_loopback(host):
        log.warning("metrics on %s: anyone who reaches that port sees user and worker names "
                    "(no token is asked there)", host)
    return metrics


def lanes_for(args: argparse.Namespace, store: Store, workers: list[Handle]) -> Lanes:
    """The scheduling over ``workers``, the store's jobs recovered into it (not started)."""
    slicing = {"slice_seconds": args.slice} if args.slice is not None else {}
    state = State(store, Scheduler(**slicing))
    recovery = Recovery(state, args.watchdog)
    recovery.recover()
    return Lanes(state, workers, args.watchdog, recovery)


def start_workers(args: argparse.Namespace, store: Store) -> Lanes:
    """The workers the machine allows, started and ready. CUDA devices that fail to start are
    left out; when none works (and none was named), one CPU worker takes their place."""
    chosen = [d.strip() for d in args.devices.split(",")] if args.devices else None
    if args.workers is not None and args.workers < 1:
        raise SystemExit(f"matoptd: --workers must be >= 1, got {args.workers}")
    try:
        per_device = sizing.parse(args.workers_per_device)
    except ValueError as exc:
        raise SystemExit(f"matoptd: --workers-per-device: {exc}")
    places = devices.placements(chosen, args.workers, args.variant, args.worker_cores,
                                per_device, args.max_samples)
    for why in dict.fromkeys(p.sizing for p in places if p.sizing):
        log.info("workers: %s", why)
    lanes, failures = _run(args, store, places)
    if not lanes.ready and places[0].cuda is not None and chosen is None \
            and args.variant is None:
        log.warning("no CUDA device works (%s); using the CPU", "; ".join(failures))
        lanes, failures = _run(args, store, devices.placements(None, 1, "llvm_ad_rgb",
                                                               args.worker_cores))
    if not lanes.ready:
        raise SystemExit("matoptd: no renderer worker started: " + "; ".join(failures))
    for failure in failures:
        log.warning("left out: %s", failure)
    return lanes


def start_ray_workers(args: argparse.Namespace, store: Store):
    """The workers of a Ray cluster, as it is now; ``ClusterWatch`` adds and retires them as
    its machines come and go. Unlike local workers, none at all is not fatal: jobs wait."""
    if args.devices:
        raise SystemExit("matoptd: --devices chooses local CUDA devices; with --ray every GPU "
                         "of the cluster is used")
    if args.workers is not None and args.workers < 1:
        raise SystemExit(f"matoptd: --workers must be >= 1, got {args.workers}")
    try:
        from .workers import ray_cluster
    except ImportError as exc:
        raise SystemExit(f"matoptd: --ray needs Ray ({exc}); pip install 'matopt-mitsuba[daemon,ray]'")
    try:
        ray_cluster.connect(args.ray)
    except Exception as exc:  # noqa: BLE001 - Ray raises many kinds; the message says which
        raise SystemExit(f"matoptd: --ray {args.ray}: cannot connect: {exc}")
    limit = _memory_limit(args, None)
    cluster = ray_cluster.ClusterWatch(
        lambda slot: ray_cluster.make_worker(slot, args.variant, store.blobs.read,
                                             args.data_dir),
        add=lambda w: lanes.add_worker(w), retire=lambda n, why: lanes.retire(n, why),
        known=lambda: lanes.state.workers, cpu_workers=args.workers, memory_limit=limit)
    lanes = lanes_for(args, store, cluster.initial())
    for failure in lanes.start():
        log.warning("left out: %s", failure)
    if not lanes.ready:
        log.warning("no worker is ready on the Ray cluster yet; jobs wait until one is")
    cluster.start()
    return lanes, cluster


def _memory_limit(args: argparse.Namespace, workers: int | None) -> int | None:
    """--worker-memory in bytes; else 80% of this machine's memory shared by ``workers``
    (None: each Ray node's own memory decides)."""
    try:
        if args.worker_memory:
            return devices.parse_size(args.worker_memory)
    except ValueError as exc:
        raise SystemExit(f"matoptd: --worker-memory: {exc}")
    return int(0.8 * devices.total_memory() / workers) if workers else None


def _run(args: argparse.Namespace, store: Store, places: list[devices.Placement]
         ) -> tuple[Lanes, list[str]]:
    limit = _memory_limit(args, len(places))
    workers = [Worker(f"workers/{i}", p,
                      args.variant or ("cuda_ad_rgb" if p.cuda is not None else "llvm_ad_rgb"),
                      args.data_dir, limit, store.blobs.read)
               for i, p in enumerate(places)]
    lanes = lanes_for(args, store, workers)
    return lanes, lanes.start()


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    logs.configure(args.log_level, args.log_format)
    args.worker_cores = None
    if args.server_cores is not None:
        # Before any thread starts: the threads gRPC and the lanes start inherit it.
        try:
            args.worker_cores = devices.reserve_cores(int(args.server_cores))
        except ValueError as exc:
            raise SystemExit(f"matoptd: --server-cores: {exc}")
        log.info("server on cores %s, workers on %s",
                 devices.core_ranges(devices.cpu_cores()),
                 devices.core_ranges(args.worker_cores))
    asyncio.run(serve(args))


if __name__ == "__main__":
    main()

"""``matoptd``: start the daemon.

    matoptd [--listen HOST:PORT] [--data-dir DIR] [--tokens FILE] [--variant V]
            [--tls-cert FILE --tls-key FILE] [--port-file FILE]

Each option can also come from the environment (MATOPTD_LISTEN, MATOPTD_DATA_DIR,
MATOPTD_TOKENS, MATOPTD_VARIANT, MATOPTD_TLS_CERT, MATOPTD_TLS_KEY).
"""

from __future__ import annotations

import argparse
import asyncio
import ipaddress
import logging
import os
import signal
import sys
from pathlib import Path

import grpc
from grpc_health.v1 import health, health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection

from . import __version__
from .auth import Authenticator, load_tokens
from .engine.variant import configure_environment
from .scheduler import Scheduler
from .server import Service, add_services
from .store import Store

log = logging.getLogger("matoptd")
MAX_MESSAGE = 64 << 20


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    env = os.environ.get
    p = argparse.ArgumentParser(prog="matoptd", description="The matopt material-"
                                "reconstruction daemon (gRPC API matopt.v1).")
    p.add_argument("--listen", default=env("MATOPTD_LISTEN", "127.0.0.1:50051"),
                   help="HOST:PORT to serve on; port 0 picks a free one (default %(default)s)")
    p.add_argument("--data-dir", type=Path,
                   default=Path(env("MATOPTD_DATA_DIR",
                                    Path.home() / ".local" / "share" / "matoptd")),
                   help="where scenes, jobs, results and blobs live (default %(default)s)")
    p.add_argument("--tokens", type=Path, default=env("MATOPTD_TOKENS"),
                   help="file of 'TOKEN USER' lines; without it only a local user, on "
                        "loopback, is served")
    p.add_argument("--variant", default=env("MATOPTD_VARIANT"),
                   help="Mitsuba variant (default: cuda_ad_rgb if a CUDA device works, else "
                        "llvm_ad_rgb)")
    p.add_argument("--tls-cert", type=Path, default=env("MATOPTD_TLS_CERT"))
    p.add_argument("--tls-key", type=Path, default=env("MATOPTD_TLS_KEY"))
    p.add_argument("--port-file", type=Path,
                   help="write the bound port here once serving (useful with port 0)")
    p.add_argument("--log-level", default=env("MATOPTD_LOG_LEVEL", "info"))
    p.add_argument("--version", action="version", version=f"matoptd {__version__}")
    return p.parse_args(argv)


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
    tokens = None
    if args.tokens:
        try:
            tokens = load_tokens(args.tokens)
        except (OSError, ValueError) as exc:
            raise SystemExit(f"matoptd: cannot use tokens file: {exc}")
    elif not is_loopback(host):
        raise SystemExit(f"matoptd: refusing to listen on {host} without --tokens: anyone "
                         "who can reach it would be the local user")
    if bool(args.tls_cert) != bool(args.tls_key):
        raise SystemExit("matoptd: --tls-cert and --tls-key go together")

    args.data_dir.mkdir(parents=True, exist_ok=True)
    # Dr.Jit reads DRJIT_CACHE_DIR and DRJIT_LIBLLVM_PATH once, when it is first imported.
    configure_environment(args.data_dir)
    store = Store(args.data_dir)
    scheduler = Scheduler(store, args.data_dir, args.variant)
    try:
        await asyncio.to_thread(scheduler.start)
    except Exception as exc:
        raise SystemExit(f"matoptd: the rendering engine did not start: {exc}")

    server = grpc.aio.server(options=[("grpc.max_receive_message_length", MAX_MESSAGE),
                                      ("grpc.max_send_message_length", MAX_MESSAGE)])
    names = add_services(server, Service(store, scheduler, Authenticator(tokens)))
    health_servicer = health.aio.HealthServicer()
    health_pb2_grpc.add_HealthServicer_to_server(health_servicer, server)
    reflection.enable_server_reflection(
        [*names, health_pb2.DESCRIPTOR.services_by_name["Health"].full_name,
         reflection.SERVICE_NAME], server)
    if args.tls_cert:
        creds = grpc.ssl_server_credentials([(args.tls_key.read_bytes(),
                                              args.tls_cert.read_bytes())])
        bound = server.add_secure_port(args.listen, creds)
    else:
        bound = server.add_insecure_port(args.listen)
    await server.start()
    for name in ["", *names]:
        await health_servicer.set(name, health_pb2.HealthCheckResponse.SERVING)
    if args.port_file:
        tmp = args.port_file.with_suffix(".tmp")
        tmp.write_text(str(bound))
        tmp.replace(args.port_file)
    log.info("matoptd %s serving on %s:%d (%s, %s, %s)", __version__, host, bound,
             scheduler.variant, "TLS" if args.tls_cert else "plaintext",
             f"{len(set(tokens.values()))} user(s)" if tokens else "local user only")

    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    await stop.wait()
    log.info("shutting down: finishing the current iteration")
    await health_servicer.enter_graceful_shutdown()
    await server.stop(grace=5)
    await asyncio.to_thread(scheduler.stop)
    store.close()
    log.info("stopped")


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    logging.basicConfig(level=args.log_level.upper(), stream=sys.stderr,
                        format="%(asctime)s %(name)s %(levelname)s %(message)s")
    asyncio.run(serve(args))


if __name__ == "__main__":
    main()

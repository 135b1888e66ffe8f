"""The gRPC server: the matopt services behind their interceptors, health and reflection.

Requests are checked in the caller's terms before any engine work is queued; engine work goes
to a worker through the lanes. This process never imports Mitsuba or Dr.Jit.
"""

from __future__ import annotations

import asyncio
import logging
from pathlib import Path
from typing import Callable

import grpc
from grpc_health.v1 import health, health_pb2, health_pb2_grpc

from matopt_api.v1 import matopt_pb2 as pb
from matopt_api.v1 import matopt_pb2_grpc as rpc

from ..scheduling.lanes import Lanes
from . import reflection
from .auth import Authenticator
from .backend import Backend
from .blob_service import BlobService
from .info_service import ServerService
from .interceptors import Authentication, Errors, Latency
from .job_service import JobService
from .scene_service import SceneService

log = logging.getLogger("matoptd.server")

MAX_MESSAGE = 64 << 20
SERVICES = ("BlobService", "SceneService", "JobService", "ServerService")


class Health(health.aio.HealthServicer):
    """grpc.health.v1.Health, List included: grpcio-health-checking's servicer advertises it
    (reflection lists it) but answers it UNIMPLEMENTED."""

    def __init__(self) -> None:
        super().__init__()
        self.statuses = {"": health_pb2.HealthCheckResponse.SERVING}

    async def set(self, service: str, status) -> None:
        self.statuses[service] = status
        await super().set(service, status)

    async def enter_graceful_shutdown(self) -> None:
        self.statuses = dict.fromkeys(self.statuses, health_pb2.HealthCheckResponse.NOT_SERVING)
        await super().enter_graceful_shutdown()

    async def List(self, request, context) -> health_pb2.HealthListResponse:
        return health_pb2.HealthListResponse(statuses={
            name: health_pb2.HealthCheckResponse(status=status)
            for name, status in self.statuses.items()})


def hidden(data_dir: Path) -> dict[str, str]:
    """The data directory, as written and as resolved, and what a message says instead."""
    return {str(p): "<data dir>" for p in {Path(data_dir), Path(data_dir).absolute(),
                                           Path(data_dir).resolve()}}


def build(backend: Backend, auth: Authenticator,
          latency: Callable[[str, str, float], None] | None = None
          ) -> tuple[grpc.aio.Server, Health, list[str]]:
    """The server with every service added; returns it, its health servicer and the names
    health reports on ("" for the whole server). ``latency``: told each call's method,
    status code and seconds (``Latency``)."""
    names = [pb.DESCRIPTOR.services_by_name[n].full_name for n in SERVICES]
    timing = [Latency(latency)] if latency is not None else []
    server = grpc.aio.server(
        interceptors=[*timing, Authentication(auth, names),
                      Errors(names, hidden(backend.store.root))],
        options=[("grpc.max_receive_message_length", MAX_MESSAGE),
                 ("grpc.max_send_message_length", MAX_MESSAGE)])
    rpc.add_BlobServiceServicer_to_server(BlobService(backend), server)
    rpc.add_SceneServiceServicer_to_server(SceneService(backend), server)
    rpc.add_JobServiceServicer_to_server(JobService(backend), server)
    rpc.add_ServerServiceServicer_to_server(ServerService(backend), server)
    health_servicer = Health()
    health_pb2_grpc.add_HealthServicer_to_server(health_servicer, server)
    reflection.enable(server, [*names, health_pb2.DESCRIPTOR.services_by_name["Health"].full_name])
    return server, health_servicer, ["", *names]


async def report_health(servicer: Health, names: list[str], lanes: Lanes,
                        stop: asyncio.Event) -> None:
    """NOT_SERVING while the service cannot do work (no worker runs, or the disk is full),
    so that a load balancer or a supervisor sees it; SERVING again when it can."""
    serving = True
    while not stop.is_set():
        now = lanes.serving
        if now != serving:
            serving = now
            status = (health_pb2.HealthCheckResponse.SERVING if now
                      else health_pb2.HealthCheckResponse.NOT_SERVING)
            for name in names:
                await servicer.set(name, status)
            log.warning("health: %s", "SERVING" if now else "NOT_SERVING")
        try:
            await asyncio.wait_for(stop.wait(), 0.5)
        except asyncio.TimeoutError:
            pass

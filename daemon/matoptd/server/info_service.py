"""ServerService: what the daemon offers and who is calling; its workers with their state."""

from __future__ import annotations

from matoptd import __version__
from matopt_api.v1 import matopt_pb2 as pb
from matopt_api.v1 import matopt_pb2_grpc as rpc

from ..engine.losses import LOSSES, OBJECTIVES
from ..settings import INTEGRATORS, SCHEDULES, SENSOR_MODES
from .backend import Backend
from .convert import worker_to_pb
from .interceptors import caller


class ServerService(rpc.ServerServiceServicer):
    def __init__(self, backend: Backend) -> None:
        self.lanes = backend.lanes

    async def GetServerInfo(self, request, context):
        user = caller()
        workers = [worker_to_pb(w) for w in self.lanes.listing(user)]
        first = next((w for w in workers if w.variant), pb.Worker())
        return pb.ServerInfo(
            version=__version__, variant=first.variant, device=first.device, user=user,
            workers=workers, losses=list(OBJECTIVES),
            loss_titles={name: LOSSES[name].title for name in OBJECTIVES},
            schedules=list(SCHEDULES), sensor_modes=list(SENSOR_MODES),
            integrators=list(INTEGRATORS),
            capabilities=["chunked-upload", "content-addressed-blobs", "pause-resume",
                          "checkpoint-resume", "watch", "render", "multi-user", "restart",
                          "ground-truth-errors", "image-error", "optimized-scene-export",
                          "worker-processes"])

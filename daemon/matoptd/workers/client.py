"""The engine interface of one worker, for the daemon: each ``engine_api.Engine`` call is made
in the worker (a process, or a Ray actor), under the watchdog's deadline, and what the engine
raised comes back as the daemon's errors. A worker that is lost meanwhile raises
``WorkerLost``, which its lane settles."""

from __future__ import annotations

from typing import Any, Protocol

from .. import engine_api as api
from ..errors import FailedPrecondition, Internal, InvalidArgument, ResourceExhausted, UserError
from ..settings import JobSettings, ReferenceInput, SceneInput
from .handle import CallFailed


class Callee(Protocol):
    """What the client needs of a worker handle (``handle.Worker``): its one way in."""

    def call(self, method: str, *args: Any, timeout: float | None = None) -> Any: ...


class EngineClient(api.Engine):
    def __init__(self, worker: Callee, timeout: float | None) -> None:
        self._worker, self._timeout = worker, timeout

    def _call(self, method: str, *args: Any) -> Any:
        try:
            return self._worker.call(method, *args, timeout=self._timeout)
        except CallFailed as exc:
            raise daemon_error(exc) from None

    def describe_scene(self, scene: SceneInput) -> api.SceneDescription:
        return self._call("describe_scene", scene)

    def render(self, scene: SceneInput, request: api.RenderRequest) -> list[api.Image]:
        return self._call("render", scene, request)

    def check_references(self, references: list[ReferenceInput]) -> None:
        return self._call("check_references", references)

    def start(self, job: str, settings: JobSettings, checkpoint: bytes | None) -> api.Started:
        return self._call("start", job, settings, checkpoint)

    def step(self, job: str, n: int) -> api.Progress:
        return self._call("step", job, n)

    def checkpoint(self, job: str) -> bytes:
        return self._call("checkpoint", job)

    def result_images(self, job: str, sensor: int) -> dict[str, list[api.Image]]:
        return self._call("result_images", job, sensor)

    def estimate_part(self, job: str, seconds: float) -> bool:
        return self._call("estimate_part", job, seconds)

    def finish(self, job: str, history: list[api.IterationRecord], cancelled: bool,
               render: bool = True) -> api.Finished:
        return self._call("finish", job, history, cancelled, render)

    def estimate(self, run: str, settings: JobSettings | None, checkpoint: bytes | None,
                 which: str, seconds: float) -> api.Estimated | None:
        return self._call("estimate", run, settings, checkpoint, which, seconds)

    def release(self, job: str) -> None:
        return self._call("release", job)


def daemon_error(exc: CallFailed) -> UserError:
    """What the engine raised, as the daemon reports it."""
    if exc.kind == "invalid":
        return InvalidArgument(str(exc))
    if exc.kind == "memory":
        return ResourceExhausted(f"out of memory: {exc}")
    if exc.kind == "engine":
        return FailedPrecondition(str(exc))
    return Internal(f"the renderer failed: {exc}")

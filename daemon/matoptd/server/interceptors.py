"""What every call of the matopt services goes through before and after its handler, as gRPC
server interceptors: who is calling (``Authentication``), and the request's fields checked and
the daemon's errors turned into status codes (``Errors``). Health and reflection, services of
their own, pass untouched. A handler reads its caller with ``caller()``.

The daemon's errors (``errors.py``) become status codes here and nowhere else: each kind its
code, with its message as it stands. Anything else that escapes a handler is INTERNAL, logged,
and confined to that one request.

RESOURCE_EXHAUSTED comes in two kinds, told apart for gRPC's own retries (which go by status
code): a limit that lifts within seconds (``Busy``) carries ``google.rpc.RetryInfo`` in the
status details and the delay as ``grpc-retry-pushback-ms``, which a client's retry policy waits
for; any other limit (a quota, a size) says so in its message and sends a pushback of -1, which
tells the retry policy not to retry.
"""

from __future__ import annotations

import asyncio
import contextlib
import contextvars
import logging
import time
from typing import Any, AsyncIterator, Awaitable, Callable, Iterator

import grpc
from google.protobuf import any_pb2, duration_pb2
from google.protobuf.message import Message
from google.rpc import error_details_pb2, status_pb2

from ..errors import (Busy, FailedPrecondition, Internal, InvalidArgument, NotFound,
                      ResourceExhausted, Unavailable, UserError)
from ..logs import about
from . import fields
from .auth import Authenticator

log = logging.getLogger("matoptd.server")

UNAUTHENTICATED = "missing or unknown token: send 'authorization: Bearer <token>'"
CODES = {InvalidArgument: grpc.StatusCode.INVALID_ARGUMENT,
         NotFound: grpc.StatusCode.NOT_FOUND,
         FailedPrecondition: grpc.StatusCode.FAILED_PRECONDITION,
         ResourceExhausted: grpc.StatusCode.RESOURCE_EXHAUSTED,
         Unavailable: grpc.StatusCode.UNAVAILABLE,
         Internal: grpc.StatusCode.INTERNAL}

NOT_RETRIED = " (not retried: it holds until the usage or the limit changes)"
PUSHBACK = "grpc-retry-pushback-ms"  # gRPC's retry policy: delay, or < 0 for "do not retry"
ATTEMPTS = "grpc-previous-rpc-attempts"  # sent by gRPC's retries
RETRY_CAP_S = 60.0

_caller: contextvars.ContextVar[str] = contextvars.ContextVar("caller")

Continuation = Callable[[grpc.HandlerCallDetails], Awaitable[grpc.RpcMethodHandler | None]]


def caller() -> str:
    """The user of the call being served (set by ``Authentication``)."""
    return _caller.get()


def code(exc: UserError) -> grpc.StatusCode:
    for kind in type(exc).__mro__:
        if kind in CODES:
            return CODES[kind]
    return grpc.StatusCode.INVALID_ARGUMENT


def status(exc: UserError, attempts: int = 0
           ) -> tuple[grpc.StatusCode, str, tuple[tuple[str, str | bytes], ...]]:
    """The status an error answers with: code, message and trailing metadata (for
    RESOURCE_EXHAUSTED, whether and when to retry). ``attempts``: how often the caller was
    refused before (gRPC's grpc-previous-rpc-attempts); each doubles the delay, as a client's
    own exponential backoff would, since a pushback takes the backoff's place."""
    kind, message = code(exc), str(exc)
    if isinstance(exc, Busy):
        wait = min(RETRY_CAP_S, exc.retry_after * 2 ** min(attempts, 8))
        delay = duration_pb2.Duration()
        delay.FromNanoseconds(round(wait * 1e9))
        detail = any_pb2.Any()
        detail.Pack(error_details_pb2.RetryInfo(retry_delay=delay))
        rich = status_pb2.Status(code=kind.value[0], message=message, details=[detail])
        return kind, message, (("grpc-status-details-bin", rich.SerializeToString()),
                               (PUSHBACK, str(max(1, round(wait * 1000)))))
    if isinstance(exc, ResourceExhausted):
        return kind, message + NOT_RETRIED, ((PUSHBACK, "-1"),)
    return kind, message, ()


def _ours(details: grpc.HandlerCallDetails, services: frozenset[str]) -> bool:
    return details.method.split("/")[1] in services  # "/matopt.v1.JobService/GetJob"


class Authentication(grpc.aio.ServerInterceptor):
    """Every call of ``services`` needs a known token; a call without one is refused with
    UNAUTHENTICATED before anything of it is read. The caller's name is kept for the handler
    (gRPC runs the interceptors and the handler in one contextvars context)."""

    def __init__(self, auth: Authenticator, services: list[str]) -> None:
        self.auth, self.services = auth, frozenset(services)

    async def intercept_service(self, continuation: Continuation,
                                details: grpc.HandlerCallDetails) -> grpc.RpcMethodHandler:
        handler = await continuation(details)
        if handler is None or not _ours(details, self.services):
            return handler
        user = self.auth.user(details.invocation_metadata)
        if user is None:
            return _wrapped(handler, _refuse, _refuse_stream)
        _caller.set(user)
        return handler


async def _refuse(request: Any, context: grpc.aio.ServicerContext) -> None:
    await context.abort(grpc.StatusCode.UNAUTHENTICATED, UNAUTHENTICATED)


async def _refuse_stream(request: Any, context: grpc.aio.ServicerContext
                         ) -> AsyncIterator[Any]:
    await context.abort(grpc.StatusCode.UNAUTHENTICATED, UNAUTHENTICATED)
    yield  # an async generator, as a streaming handler is


class Latency(grpc.aio.ServerInterceptor):
    """Times every call (a stream until its last message) and hands the method, the status
    code and the seconds to ``observe``, which must not raise (``metrics.Metrics.rpc``).
    First of the interceptors, so that a call refused by the others is timed too."""

    def __init__(self, observe: Callable[[str, str, float], None]) -> None:
        self.observe = observe

    async def intercept_service(self, continuation: Continuation,
                                details: grpc.HandlerCallDetails) -> grpc.RpcMethodHandler:
        handler = await continuation(details)
        if handler is None:
            return handler
        method = details.method.lstrip("/")
        if handler.response_streaming:
            inner_stream = handler.unary_stream

            async def stream(request, context):
                with self._timed(method, context):
                    async for item in inner_stream(request, context):
                        yield item
            return _wrapped(handler, None, stream)
        inner = handler.unary_unary or handler.stream_unary

        async def unary(request, context):
            with self._timed(method, context):
                return await inner(request, context)
        return _wrapped(handler, unary, None)

    @contextlib.contextmanager
    def _timed(self, method: str, context: grpc.aio.ServicerContext) -> Iterator[None]:
        """Observes the call's time and status when the block ends, however it ends."""
        began = time.perf_counter()
        try:
            yield
        except BaseException as exc:
            self._observe(method, context, exc, began)
            raise
        self._observe(method, context, None, began)

    def _observe(self, method: str, context: grpc.aio.ServicerContext,
                 failure: BaseException | None, began: float) -> None:
        try:
            self.observe(method, _code(context, failure), time.perf_counter() - began)
        except Exception:  # noqa: BLE001 - a metric must never cost a call its answer
            log.exception("metrics: could not time a call of %s", method)


def _code(context: grpc.aio.ServicerContext, failure: BaseException | None) -> str:
    """The call's status code by name: the one a handler or an interceptor set, else OK, or
    what gRPC answers for an exception that escaped (CANCELLED, UNKNOWN)."""
    code = context.code()
    if code is None:
        if failure is None:
            return "OK"
        gone = isinstance(failure, (asyncio.CancelledError, GeneratorExit))  # caller left
        return "CANCELLED" if gone else "UNKNOWN"
    if isinstance(code, grpc.StatusCode):
        return code.name
    return next((c.name for c in grpc.StatusCode if c.value[0] == code), str(code))


class Errors(grpc.aio.ServerInterceptor):
    """Checks each request's fields (``fields.check``) and answers the daemon's errors with
    their status codes, around every handler of ``services``. ``hidden``: the daemon's own
    paths (its data directory) and the words that stand for them in a message: no answer
    shows a caller where the daemon keeps anything."""

    def __init__(self, services: list[str], hidden: dict[str, str] | None = None) -> None:
        self.services = frozenset(services)
        self.hidden = hidden or {}

    async def intercept_service(self, continuation: Continuation,
                                details: grpc.HandlerCallDetails) -> grpc.RpcMethodHandler:
        handler = await continuation(details)
        if handler is None or not _ours(details, self.services):
            return handler
        if handler.response_streaming:
            inner_stream = handler.unary_stream

            async def stream(request, context):
                await _guard(context, lambda: _check(request), self.hidden)
                responses = inner_stream(request, context).__aiter__()
                while (item := await _guard(context, lambda: _next(responses),
                                            self.hidden)) is not _END:
                    yield item
            return _wrapped(handler, None, stream)
        inner = handler.unary_unary or handler.stream_unary

        async def unary(request, context):
            await _guard(context, lambda: _check(request), self.hidden)
            return await _guard(context, lambda: inner(request, context), self.hidden)
        return _wrapped(handler, unary, None)


_END = object()


async def _check(request: Any) -> None:
    if isinstance(request, Message):  # not the chunk stream of UploadBlob
        fields.check(request)


async def _next(responses: AsyncIterator[Any]) -> Any:
    try:
        return await responses.__anext__()
    except StopAsyncIteration:
        return _END


async def _guard(context: grpc.aio.ServicerContext, fn: Callable[[], Awaitable[Any]],
                 hidden: dict[str, str]) -> Any:
    """Runs one step of a handler, turning the daemon's errors into statuses."""
    try:
        return await fn()
    except UserError as exc:
        kind, message, trailers = status(exc, _attempts(context))
        await context.abort(kind, hide(message, hidden), trailers)
    except (grpc.aio.AbortError, asyncio.CancelledError):
        raise
    except Exception as exc:  # noqa: BLE001 - one bad request must not take others down
        log.exception("internal error", extra=about(user=_caller.get(None)))
        await context.abort(grpc.StatusCode.INTERNAL,
                            hide(f"internal error: {type(exc).__name__}: {exc}", hidden))


def hide(message: str, hidden: dict[str, str]) -> str:
    """``message`` with each hidden path (longest first: a folder inside another) replaced by
    the words that stand for it."""
    for path in sorted(hidden, key=len, reverse=True):
        message = message.replace(path, hidden[path])
    return message


def _attempts(context: grpc.aio.ServicerContext) -> int:
    for key, value in context.invocation_metadata() or ():
        if key == ATTEMPTS:
            try:
                return int(value)
            except ValueError:
                return 0
    return 0


def _wrapped(handler: grpc.RpcMethodHandler, unary: Callable | None,
             stream: Callable | None) -> grpc.RpcMethodHandler:
    """The handler with its behaviour replaced: ``unary`` for a single response (a single
    request or a stream of them), ``stream`` for a response stream. This API has no call
    with streams both ways."""
    kinds = {"request_deserializer": handler.request_deserializer,
             "response_serializer": handler.response_serializer}
    if handler.response_streaming:
        return grpc.unary_stream_rpc_method_handler(stream, **kinds)
    if handler.request_streaming:
        return grpc.stream_unary_rpc_method_handler(unary, **kinds)
    return grpc.unary_unary_rpc_method_handler(unary, **kinds)

"""Errors that reach the user as a gRPC status: the code says what kind, the message says which
file, key or value. Everything else that escapes a handler is INTERNAL."""

from __future__ import annotations

import grpc


class UserError(Exception):
    code = grpc.StatusCode.INVALID_ARGUMENT


class InvalidArgument(UserError):
    code = grpc.StatusCode.INVALID_ARGUMENT


class NotFound(UserError):
    code = grpc.StatusCode.NOT_FOUND


class FailedPrecondition(UserError):
    code = grpc.StatusCode.FAILED_PRECONDITION


class AlreadyExists(UserError):
    code = grpc.StatusCode.ALREADY_EXISTS


class ResourceExhausted(UserError):
    code = grpc.StatusCode.RESOURCE_EXHAUSTED


class Unavailable(UserError):
    """The service cannot do this now (shutting down, no renderer running); try again."""
    code = grpc.StatusCode.UNAVAILABLE


class Internal(UserError):
    """Not the caller's fault, but with a message that says what happened (a renderer process
    that died while serving the request), rather than a traceback's last line."""
    code = grpc.StatusCode.INTERNAL


class DiskFull(ResourceExhausted):
    """The data directory's disk is full: nothing of the request was stored. The daemon holds
    its jobs and goes on by itself once space is freed."""

    def __init__(self) -> None:
        super().__init__("the daemon's disk is full: nothing was stored; running jobs are held "
                         "and go on by themselves once space is freed")

"""The daemon's errors in its own terms: the class says what kind of failure, the message says
which file, key or value. The API's edge maps each kind to a gRPC status code, in one place
(``server/interceptors.py``); the store, the scheduling and the workers never see gRPC."""

from __future__ import annotations


class UserError(Exception):
    """A failure whose message is for the user as it stands (the caller's request, or what
    happened to it); anything else that escapes a request is an internal error."""


class InvalidArgument(UserError):
    """The request is wrong whatever the daemon's state: a bad value, file or key."""


class NotFound(UserError):
    """No such scene, job or blob, or not the caller's (the same message either way)."""


class FailedPrecondition(UserError):
    """The request does not fit the state it meets: resuming a finished job, deleting a scene
    that unfinished jobs use."""


class ResourceExhausted(UserError):
    """Over a limit that protects the other users: a quota, a budget of samples or jobs.
    Retrying at once does not lift it (clients do not retry it); ``Busy`` is the kind that
    does."""


class Busy(ResourceExhausted):
    """Over a limit that lifts by itself within seconds (too many of the caller's requests in
    progress): the answer says when to try again, and clients retry by themselves."""

    def __init__(self, message: str, retry_after: float) -> None:
        super().__init__(message)
        self.retry_after = retry_after  # seconds


class Unavailable(UserError):
    """The service cannot do this now (shutting down, no renderer running); try again."""


class Internal(UserError):
    """Not the caller's fault, but with a message that says what happened (a renderer process
    that died while serving the request), rather than a traceback's last line."""


class DiskFull(ResourceExhausted):
    """The data directory's disk is full: nothing of the request was stored. The daemon holds
    its jobs and goes on by itself once space is freed."""

    def __init__(self) -> None:
        super().__init__("the daemon's disk is full: nothing was stored; running jobs are held "
                         "and go on by themselves once space is freed")

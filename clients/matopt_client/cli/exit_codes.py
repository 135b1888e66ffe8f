"""The exit statuses of ``matopt``, declared once.

A script tells from the status alone whether to fix its own command line and files (2) or
to read what the daemon said (1). The error handler (``Main.main``), the top-level ``--help``
and docs/cli.md all take the statuses and their meanings from here.
"""

from __future__ import annotations

import click
import grpc

from matopt_api.bundle import BundleError
from matopt_client.client import ClientError, LocalFileError, error_message

OK = 0
DAEMON = 1
USAGE = 2
INTERRUPTED = 130

MEANINGS: dict[int, str] = {
    OK: "success.",
    DAEMON: "the daemon refused a request (the message starts with the gRPC status code "
            "name, e.g. NOT_FOUND, then the daemon's own message), no daemon answered, or "
            "a job followed with --wait or 'job watch' did not succeed; also any other "
            "failure after the command line and its files were accepted.",
    USAGE: "a usage error (an unknown option, a missing argument, a malformed value), or a "
           "local file or folder that is missing, unreadable or invalid (a scene XML or a "
           "file it names, a --ref image, a .npy, the TLS CA, an --out folder that is not "
           "empty).",
    INTERRUPTED: "interrupted (Ctrl-C); a job being followed keeps running on the daemon.",
}


# What ends a command with a message rather than a traceback (anything else is a bug).
HANDLED = (click.ClickException, click.Abort, KeyboardInterrupt, grpc.RpcError, ClientError,
           BundleError, OSError)


def failure(exc: BaseException) -> tuple[str, int]:
    """The one-line message and the exit status of one of the ``HANDLED`` exceptions."""
    if isinstance(exc, click.ClickException):  # UsageError is one, with exit_code 2
        return exc.format_message(), exc.exit_code
    if isinstance(exc, (click.Abort, KeyboardInterrupt)):
        return "interrupted", INTERRUPTED
    if isinstance(exc, grpc.RpcError):
        return error_message(exc), DAEMON
    if isinstance(exc, (LocalFileError, BundleError)):
        return str(exc), USAGE
    if isinstance(exc, ClientError):  # Unreachable, a corrupt download, a private daemon
        return str(exc), DAEMON
    if isinstance(exc, OSError):  # a local file: --out not writable, a file gone meanwhile
        where = f"'{exc.filename}': " if exc.filename else ""
        return f"{where}{exc.strerror or exc}", USAGE
    raise exc

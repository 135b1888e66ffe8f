"""``matopt``: the command line client of matoptd.

Every failure ends in one line on stderr (``matopt: error: NOT_FOUND: job 'jobs/x' not found``)
and a non-zero exit status, never a traceback; the statuses are declared in ``exit_codes``.
"""

from __future__ import annotations

import os
import sys

# gRPC's C core logs connection failures to stderr on its own; the CLI reports them itself,
# in one line. Must be set before grpc is first imported.
os.environ.setdefault("GRPC_VERBOSITY", "ERROR")

import click  # noqa: E402

from matopt_client import __version__, workers
from matopt_api.v1 import matopt_pb2 as pb
from matopt_client.cli import exit_codes
from matopt_client.cli.output import emit_json, fields, json_option
from matopt_client.cli.session import Group, Settings, connected, root_options


def _fail(message: str, code: int) -> int:
    one_line = " ".join(message.split())  # a daemon's error may carry a multi-line traceback
    click.echo(f"matopt: error: {one_line}", err=True)
    return code


class _ReaderGone(Exception):
    """stdout's reader has gone: an exception click lets through to :meth:`Main.main`."""


def _reader_gone() -> int:
    """stdout's reader stopped reading (``matopt info | head -1``): that is how such a pipe
    ends, not an error. What is still buffered goes nowhere, so that the interpreter's own
    flush at exit cannot fail in turn."""
    os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
    return 0


def _usage_message(exc: click.UsageError) -> str:
    text = exc.format_message()
    if exc.ctx is not None:
        text += f" (see '{exc.ctx.command_path} --help')"
    return text


class Main(Group):
    """The ``matopt`` group; its :meth:`main` turns every exception into one line and a status.

    Doing it here, rather than around the call in :func:`main`, also covers callers that run
    the group directly (click's test runner, ``python -m``).
    """

    def format_epilog(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        """The exit statuses after the commands, where a script's author looks for them."""
        super().format_epilog(ctx, formatter)
        with formatter.section("Exit status"):
            formatter.write_dl([(str(code), text) for code, text in
                                exit_codes.MEANINGS.items()])

    # click answers a closed pipe with exit status 1: it is told of one as something else.
    def make_context(self, *args, **kwargs) -> click.Context:
        try:
            return super().make_context(*args, **kwargs)  # --help prints from here
        except BrokenPipeError:
            raise _ReaderGone() from None

    def invoke(self, ctx: click.Context):
        try:
            return super().invoke(ctx)
        except BrokenPipeError:
            raise _ReaderGone() from None

    def main(self, args=None, prog_name=None, complete_var=None, standalone_mode=True, **extra):
        try:
            result = super().main(args, prog_name or "matopt", complete_var,
                                  standalone_mode=False, **extra)
            code = result if isinstance(result, int) else 0
            sys.stdout.flush()  # here, where a closed pipe is caught, not at exit
        except (BrokenPipeError, _ReaderGone):
            code = _reader_gone()
        except click.UsageError as exc:
            code = _fail(_usage_message(exc), exc.exit_code)
        except exit_codes.HANDLED as exc:
            code = _fail(*exit_codes.failure(exc))
        if standalone_mode:
            sys.exit(code)
        return code


@click.group("matopt", cls=Main, context_settings={"help_option_names": ["-h", "--help"]})
@root_options
@click.version_option(__version__, prog_name="matopt")
@click.pass_context
def cli(ctx: click.Context, server: str, token: str | None, tls_ca: str | None) -> None:
    """Material reconstruction with matoptd: load scenes, run and follow optimization jobs.

    Connection options go before the command (matopt --server H:P job list) or after it.
    SCENE and JOB are full names (scenes/abc, jobs/abc) or bare ids (abc).

    Shell completion of commands, options and your scene and job ids, for bash:
    eval "$(_MATOPT_COMPLETE=bash_source matopt)" in ~/.bashrc (zsh, fish: docs/cli.md).
    """
    ctx.obj = Settings(server=server, token=token or None, tls_ca=tls_ca or None)


@cli.command()
@json_option
def info(as_json: bool) -> None:
    """Show what the daemon runs.

    Version, Mitsuba variant, device, the user your token belongs to, the losses, schedules
    and sensor modes jobs accept, integrators, and its renderer workers: state, device,
    process, memory against its limit, jobs (only yours by name) and restarts.
    """
    client = connected()
    info = client.info or client.server.GetServerInfo(pb.GetServerInfoRequest())
    if as_json:
        emit_json(info)
        return
    fields({
        "server": client.target,
        "version": info.version,
        "variant": info.variant,
        "device": info.device,
        "user": info.user,
        # Lists an older daemon does not announce are left out rather than shown empty.
        "losses": ", ".join(info.losses) or None,
        "schedules": ", ".join(info.schedules) or None,
        "sensor modes": ", ".join(info.sensor_modes) or None,
        "integrators": ", ".join(info.integrators) or None,
        "capabilities": ", ".join(info.capabilities) or None,
        # A daemon older than the workers list reports none: say nothing rather than "none".
        "workers": workers.summary(info.workers) if info.workers else None,
        # Workers sharing a device: how many, and why that many.
        "per device": "; ".join(dict.fromkeys(w.sizing for w in info.workers if w.sizing))
        or None,
    })
    for line in workers.worker_lines(info.workers, info.variant):
        click.echo(f"  {line}")


def _register() -> None:
    from matopt_client.cli import blob, demo, job, scene

    cli.add_command(scene.scene)
    cli.add_command(job.job)
    cli.add_command(blob.blob)
    cli.add_command(demo.demo)


_register()


def main() -> None:
    """The console script ``matopt``."""
    cli.main(prog_name="matopt")

"""Where the CLI connects: the --server/--token/--tls-ca options and the lazily opened client.

The options are read on the ``matopt`` group (with their environment variables) and accepted
again after any subcommand, where they override, so both ``matopt --server X job list`` and
``matopt job list --server X`` work. Commands that need the daemon ask for the client
(see :func:`connected`) only once their arguments are checked; ``--help`` and argument errors
therefore never connect.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Callable

import click

from matopt_client.client import DEFAULT_PORT, DEFAULT_SERVER, Client, connect

_OPTIONS = {  # name -> (environment variable, help)
    "server": ("MATOPT_SERVER", f"matoptd address, host:port (port {DEFAULT_PORT} if left out)"),
    "token": ("MATOPT_TOKEN", "access token, sent as 'authorization: Bearer <token>'"),
    "tls_ca": ("MATOPT_TLS_CA", "PEM file of the CA that signed the daemon's certificate; "
                                "enables TLS"),
}

CONNECTION_OPTIONS = frozenset(_OPTIONS)  # the parameter names, as every command has them


@dataclass
class Settings:
    """The connection settings of one CLI invocation, and its client once connected."""

    server: str = field(default_factory=lambda: os.environ.get("MATOPT_SERVER") or DEFAULT_SERVER)
    token: str | None = field(default_factory=lambda: os.environ.get("MATOPT_TOKEN") or None)
    tls_ca: str | None = field(default_factory=lambda: os.environ.get("MATOPT_TLS_CA") or None)
    _client: Client | None = None

    def client(self) -> Client:
        if self._client is None:
            self._client = connect(self.server, self.token, self.tls_ca)
            click.get_current_context().find_root().call_on_close(self._client.close)
        return self._client


def _flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def root_options(f: Callable) -> Callable:
    """The connection options of the ``matopt`` group, with environment variables and defaults."""
    for name, (env, help_) in reversed(_OPTIONS.items()):
        default = DEFAULT_SERVER if name == "server" else None
        f = click.option(_flag(name), name, envvar=env, default=default, show_default=True,
                         show_envvar=True, help=help_)(f)
    return f


_OVERRIDDEN = "matopt.overridden"  # ctx.meta key: the options given after a subcommand


def _override(ctx: click.Context, param: click.Parameter, value: str | None) -> None:
    if value is not None:
        setattr(ctx.ensure_object(Settings), param.name, value)
        ctx.meta.setdefault(_OVERRIDDEN, {})[param.name] = value


def _override_options() -> list[click.Option]:
    """Fresh copies for one command (click must not share Option objects between commands)."""
    return [click.Option([_flag(name), name], default=None, expose_value=False,
                         is_eager=True, callback=_override, help=f"{help_} [env: {env}]")
            for name, (env, help_) in _OPTIONS.items()]


class Group(click.Group):
    """A click group whose commands (and subgroups) all accept the connection options too."""

    group_class = type  # subgroups made with @group.group() are of this class as well

    def add_command(self, cmd: click.Command, name: str | None = None) -> None:
        present = {p.name for p in cmd.params}
        cmd.params.extend(o for o in _override_options() if o.name not in present)
        super().add_command(cmd, name)


def completion_settings(ctx: click.Context) -> Settings:
    """The settings while the shell completes a word: the group's callback, which makes
    them, does not run then, so they come from what was parsed (options, environment)."""
    given = ctx.find_root().params
    settings = Settings(server=given.get("server") or DEFAULT_SERVER,
                        token=given.get("token") or None, tls_ca=given.get("tls_ca") or None)
    for name, value in ctx.meta.get(_OVERRIDDEN, {}).items():
        setattr(settings, name, value)
    return settings


def connected() -> Client:
    """The invocation's client, connecting on first use.

    Commands call this after checking their own arguments, so a wrong command line is
    reported as such even when no daemon is running.
    """
    return click.get_current_context().ensure_object(Settings).client()

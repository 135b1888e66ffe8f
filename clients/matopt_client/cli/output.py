"""How the CLI prints: tables for people, JSON for scripts, notes on stderr.

Everything a script might parse goes to stdout (names, ``--json``); progress and warnings go to
stderr, so ``name=$(matopt scene load x.xml)`` captures just the name.
"""

from __future__ import annotations

import json
from datetime import timezone
from typing import Any, Iterable, Sequence

import click
from google.protobuf import json_format
from google.protobuf.message import Message

from matopt_client import workflow
# Shared with the Qt app; imported from here by the CLI's modules.
from matopt_client.workflow import number, parameter_error  # noqa: F401

json_option = click.option("--json", "as_json", is_flag=True, help="print JSON for scripts")


def message_dict(message: Message) -> dict[str, Any]:
    """The proto3 JSON mapping (lowerCamelCase keys, enums by name), with every field present.

    Fields at their default value are kept, so a script can read ``iteration`` of a job that
    has not started yet instead of finding the key missing.
    """
    return json_format.MessageToDict(message, always_print_fields_with_no_presence=True)


def emit_json(data: Message | dict | list, *, compact: bool = False) -> None:
    """Prints one JSON document on stdout; ``compact`` keeps it on one line (for streams)."""
    if isinstance(data, Message):
        data = message_dict(data)
    text = json.dumps(data, separators=(",", ":")) if compact else json.dumps(data, indent=2)
    click.echo(text)


def note(text: str) -> None:
    """A message for the person at the terminal, not for a script reading stdout."""
    click.echo(text, err=True)


def warn(text: str) -> None:
    click.echo(f"matopt: warning: {text}", err=True)


def table(headers: Sequence[str], rows: Iterable[Sequence[Any]]) -> None:
    """Left-aligned columns sized to their content; empty tables still print the header."""
    cells = [list(map(str, headers))] + [["" if c is None else str(c) for c in r] for r in rows]
    widths = [max(len(row[i]) for row in cells) for i in range(len(headers))]
    for row in cells:
        click.echo("  ".join(c.ljust(w) for c, w in zip(row, widths)).rstrip())


def fields(pairs: dict[str, Any]) -> None:
    """``name: value`` lines with the values aligned, for one object; None values are left out."""
    pairs = {k: v for k, v in pairs.items() if v is not None}
    width = max((len(k) for k in pairs), default=0) + 1
    for key, value in pairs.items():
        click.echo(f"{key + ':':<{width}} {value}".rstrip())


def size(n: int) -> str:
    """A byte count as people read it: 812 B, 3.4 KiB, 2.9 MiB, 20.0 GiB."""
    if n < 1024:
        return f"{n} B"
    if n < 1024**2:
        return f"{n / 1024:.1f} KiB"
    if n < 1024**3:
        return f"{n / 1024**2:.1f} MiB"
    return f"{n / 1024**3:.1f} GiB"


def uploading(label: str, n: int) -> None:
    """The ``on_upload`` callback of the client library, for the terminal."""
    note(f"uploading {label} ({size(n)})")


def best(job) -> str | None:
    """A job's best loss and where it was reached (the daemon's); None before its first
    iteration."""
    reached = workflow.best(job)
    return None if reached is None else f"{number(reached[1])} at iteration {reached[0]}"


def values(components: Sequence[float], limit: int = 4) -> str:
    """A short vector in a table cell; long ones only by their size."""
    if not components:
        return ""
    if len(components) > limit:
        return f"({len(components)} values)"
    return ", ".join(number(v) for v in components)


def timestamp(ts) -> str:
    """A protobuf Timestamp in local time, or empty when unset."""
    if not ts.seconds and not ts.nanos:
        return ""
    return ts.ToDatetime(tzinfo=timezone.utc).astimezone().strftime("%Y-%m-%d %H:%M:%S")

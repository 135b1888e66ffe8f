"""How the CLI prints: tables for people, JSON for scripts, notes on stderr.

Everything a script might parse goes to stdout (names, ``--json``); progress and warnings go to
stderr, so ``name=$(matopt scene load x.xml)`` captures just the name.
"""

from __future__ import annotations

import json
import os
import shutil
import sys
from datetime import timezone
from typing import Any, Iterable, Sequence

import click
from google.protobuf import json_format
from google.protobuf.message import Message
from tabulate import tabulate

from matopt_client import workflow
# Shared with the Qt app; imported from here by the CLI's modules.
from matopt_client.workflow import number, parameter_error, stop_reason  # noqa: F401

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


def deleted(names: Sequence[str], as_json: bool) -> None:
    """What a delete command removed: ``{"deleted": [...]}`` for scripts, a line each on
    stderr for people (stdout stays empty, as nothing was made)."""
    if as_json:
        emit_json({"deleted": list(names)})
    else:
        for name in names:
            note(f"deleted {name}")


def note(text: str) -> None:
    """A message for the person at the terminal, not for a script reading stdout."""
    click.echo(text, err=True)


def warn(text: str) -> None:
    click.echo(f"matopt: warning: {text}", err=True)


def terminal_width() -> int | None:
    """The columns output is fitted to: ``COLUMNS`` when set, else the terminal's; None (no
    limit) when stdout goes to a file or a pipe, where wrapped rows would only get in the way
    of grep."""
    if os.environ.get("COLUMNS", "").isdigit():
        return int(os.environ["COLUMNS"])
    if sys.stdout.isatty():
        return shutil.get_terminal_size().columns
    return None


def _columns(rows: list[list[str]], width: int | None, floors: list[int]) -> str | None:
    """The rows as left-aligned columns two spaces apart, at most ``width`` wide (None: any),
    by wrapping the column with the most to give first, none below its floor; None if they
    do not fit."""
    def render(limits: list[int | None]) -> str:
        return tabulate(rows, tablefmt="plain", disable_numparse=True, maxcolwidths=limits)

    def widest(text: str) -> int:
        return max(map(len, text.splitlines()), default=0)

    current = [max(len(line) for cell in column for line in cell.splitlines() or [""])
               for column in zip(*rows)]
    limits: list[int | None] = [None] * len(current)
    text = render(limits)
    while width is not None and widest(text) > width:
        i = max(range(len(current)), key=lambda k: current[k] - floors[k])
        if current[i] <= floors[i]:
            return None
        current[i] = limits[i] = max(floors[i], current[i] - (widest(text) - width))
        text = render(limits)
    return text


def _longest_words(rows: list[list[str]]) -> list[int]:
    return [max((len(w) for cell in column for w in cell.split()), default=0)
            for column in zip(*rows)]


def _pairs(rows: list[list[str]], width: int | None) -> str:
    """``name: value`` lines; values wrap at spaces, within a word only where one is
    longer than the room left."""
    name = max(len(r[0]) for r in rows)
    return (_columns(rows, width, [name, _longest_words(rows)[1]])
            or _columns(rows, width, [name, 8]) or _columns(rows, None, [name, 0]))


def table(headers: Sequence[str], rows: Iterable[Sequence[Any]]) -> None:
    """Left-aligned columns sized to their content, empty tables with their header.

    Fitted to the terminal: cells wrap at spaces (the first column, what a row is about,
    never); where the columns cannot fit that way, each row becomes a block of
    ``HEADER: value`` lines, so that no word is cut.
    """
    cells = [list(map(str, headers))] + [["" if c is None else str(c) for c in r] for r in rows]
    width = terminal_width()
    floors = _longest_words(cells)
    floors[0] = max(len(line) for row in cells for line in row[0].splitlines() or [""])
    text = _columns(cells, width, floors)
    if text is None:
        text = "\n\n".join(_pairs([[f"{h}:", c] for h, c in zip(cells[0], row)], width)
                            for row in cells[1:]) or "  ".join(cells[0])
    click.echo(text)


def fields(pairs: dict[str, Any]) -> None:
    """``name: value`` lines with the values aligned, for one object; None values are left
    out, long values wrap within the terminal's width."""
    rows = [[f"{k}:", str(v)] for k, v in pairs.items() if v is not None]
    if rows:
        click.echo("\n".join(line.rstrip() for line in
                             _pairs(rows, terminal_width()).splitlines()))


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

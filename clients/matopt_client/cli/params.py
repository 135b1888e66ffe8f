"""Parsing of the CLI's argument syntaxes (KEY=v1,v2, KEY=MIN:MAX, [N=]IMG; NAME=VALUE is
``workflow.parse_overrides``, shared with the Qt app).

Only the syntax is checked here: whether a key exists or a value is legal is the daemon's to
say, so that the CLI and the daemon can never disagree about it.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from typing import Any

import click

from matopt_client.client import resource_name


class ResourceName(click.ParamType):
    """A scene, job or blob argument: the full name (``jobs/abc``) or the bare id (``abc``)."""

    def __init__(self, collection: str) -> None:
        self.collection = collection
        self.name = collection[:-1].upper()  # "SCENE", "JOB": the metavar in --help

    def convert(self, value: Any, param, ctx) -> str:
        if not value:
            self.fail("must not be empty", param, ctx)
        return resource_name(self.collection, str(value))

    def shell_complete(self, ctx: click.Context, param: click.Parameter,
                       incomplete: str) -> list:
        """The caller's names, asked of the daemon (nothing if it does not answer at once)."""
        from matopt_client.cli import completion  # only when a shell asks

        return completion.names(self.collection, ctx, incomplete)


SCENE = ResourceName("scenes")
JOB = ResourceName("jobs")
BLOB = ResourceName("blobs")


def _split(value: str, syntax: str, param, ctx, kind: click.ParamType) -> tuple[str, str]:
    key, sep, rest = value.partition("=")
    if not sep or not key:
        kind.fail(f"'{value}' is not of the form {syntax}", param, ctx)
    return key, rest


def _float(text: str, whole: str, param, ctx, kind: click.ParamType) -> float:
    try:
        return float(text)
    except ValueError:
        kind.fail(f"'{text}' in '{whole}' is not a number", param, ctx)


@dataclass(frozen=True)
class ValueArg:
    """A parameter value from the command line: inline components, or a .npy file to upload."""

    key: str
    values: tuple[float, ...] = ()
    npy: str | None = None


class Values(click.ParamType):
    """``KEY=v1,v2,...`` (flat components), or with ``npy`` also ``KEY=@file.npy`` (or
    ``KEY=file.npy``): a texture's or grid's values do not fit on a command line."""

    def __init__(self, npy: bool = False) -> None:
        self.npy = npy
        self.name = "KEY=V1,V2,..." + ("|@FILE.npy" if npy else "")

    def convert(self, value: Any, param, ctx) -> ValueArg:
        if isinstance(value, ValueArg):
            return value
        key, rest = _split(str(value), "KEY=V1,V2,...", param, ctx, self)
        if self.npy and (rest.startswith("@") or rest.lower().endswith(".npy")):
            return ValueArg(key, npy=rest.removeprefix("@"))
        parts = [p for p in rest.replace(" ", "").split(",") if p]
        if not parts:
            self.fail(f"'{value}' gives no values", param, ctx)
        return ValueArg(key, tuple(_float(p, value, param, ctx, self) for p in parts))


class LearningRate(click.ParamType):
    """``KEY=RATE`` for one parameter, or a bare ``RATE`` for every parameter without its own."""

    name = "[KEY=]RATE"

    def convert(self, value: Any, param, ctx) -> tuple[str | None, float]:
        if isinstance(value, tuple):
            return value
        text = str(value)
        if "=" not in text:
            return None, _float(text, text, param, ctx, self)
        key, rest = _split(text, self.name, param, ctx, self)
        return key, _float(rest, text, param, ctx, self)


class Range(click.ParamType):
    """``KEY=MIN:MAX``; either bound may be left out (``KEY=0:`` sets only the minimum)."""

    name = "KEY=MIN:MAX"

    def convert(self, value: Any, param, ctx) -> tuple[str, float | None, float | None]:
        if isinstance(value, tuple):
            return value
        text = str(value)
        key, rest = _split(text, self.name, param, ctx, self)
        low, sep, high = rest.partition(":")
        if not sep:
            self.fail(f"'{text}' is not of the form {self.name}", param, ctx)
        return (key, _float(low, text, param, ctx, self) if low else None,
                _float(high, text, param, ctx, self) if high else None)


_SENSOR_PREFIX = re.compile(r"^(\d+)=(.+)$")


class ReferenceImage(click.ParamType):
    """``IMG`` (next sensor in order) or ``N=IMG`` (sensor N); IMG may be ``blobs/<sha256>``.

    A file whose name really is ``1=x.png`` is taken as a file, not as sensor 1.
    """

    name = "[SENSOR=]IMAGE"

    def convert(self, value: Any, param, ctx) -> tuple[int | None, str]:
        if isinstance(value, tuple):
            return value
        text = str(value)
        match = _SENSOR_PREFIX.match(text)
        if match and not os.path.exists(text):
            return int(match.group(1)), match.group(2)
        return None, text




class SppPhase(click.ParamType):
    """``ITER:SPP``: from iteration ITER on, SPP samples per pixel (JobSpec.spp_from)."""

    name = "ITER:SPP"

    def convert(self, value: Any, param, ctx) -> tuple[int, int]:
        if isinstance(value, tuple):
            return value
        first, _, spp = str(value).partition(":")
        try:
            return int(first), int(spp)
        except ValueError:
            self.fail(f"'{value}' is not ITER:SPP (two whole numbers, e.g. 16:64)", param, ctx)

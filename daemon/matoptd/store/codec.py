"""The records as JSON: a dataclass becomes an object of its fields, an enum its value, a numpy
array a list; reading one back follows the dataclass's type hints, so a record comes back as
the same types it was written from.

Fields missing from a stored object take their defaults, so a field added to a record later
reads from rows written before it. A decoder per type is built once and kept: a history page
decodes thousands of records.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import json
import types
import typing
from typing import Any, Callable

import numpy as np

Decoder = Callable[[Any], Any]


def dumps(obj: Any) -> str:
    # NaN and infinities as JavaScript spells them: Python's json reads them back (a PSNR of
    # an exact estimate is +inf).
    return json.dumps(encode(obj), separators=(",", ":"))


def loads(cls: type, text: str) -> Any:
    return decoder(cls)(json.loads(text))


PLAIN = frozenset({str, int, float, bool, type(None)})


def encode(obj: Any) -> Any:
    t = type(obj)
    if t in PLAIN:  # first: most of a record is plain values
        return obj
    if t is list or t is tuple:
        return [encode(v) for v in obj]
    if t is dict:
        return {k if type(k) is str else str(k): encode(v) for k, v in obj.items()}
    if isinstance(obj, enum.Enum):
        return obj.value
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if dataclasses.is_dataclass(obj):
        return {name: encode(getattr(obj, name)) for name in _names(t)}
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


@functools.cache
def _names(cls: type) -> tuple[str, ...]:
    return tuple(f.name for f in dataclasses.fields(cls))


@functools.cache
def decoder(hint: Any) -> Decoder:
    """A function from decoded JSON to an object of type ``hint``."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        inner = [a for a in args if a is not type(None)]
        if len(inner) != 1:
            raise TypeError(f"cannot decode {hint}")
        one = decoder(inner[0])
        return lambda v: None if v is None else one(v)
    if origin in (list, tuple):
        item = decoder(args[0])
        return (lambda v: [item(x) for x in v]) if origin is list else (
            lambda v: tuple(item(x) for x in v))
    if origin is dict:
        key, value = decoder(args[0]), decoder(args[1])
        return lambda v: {key(k): value(x) for k, x in v.items()}
    if hint is np.ndarray:
        return lambda v: np.asarray(v, dtype=np.float32)
    if isinstance(hint, type) and issubclass(hint, enum.Enum):
        return hint
    if dataclasses.is_dataclass(hint):
        return _dataclass(hint)
    if hint in (int, float, str, bool):
        return hint
    if hint is Any:
        return lambda v: v
    raise TypeError(f"cannot decode {hint}")


def _dataclass(cls: type) -> Decoder:
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    parts: dict[str, Decoder] = {}

    def decode(v: dict | Any) -> Any:
        if isinstance(v, cls):  # decoded already (a part the caller keeps decoded)
            return v
        if not parts:  # built on first use: a record may refer to its own type
            parts.update({name: decoder(hints[name]) for name in fields})
        return cls(**{name: parts[name](x) for name, x in v.items() if name in fields})
    return decode

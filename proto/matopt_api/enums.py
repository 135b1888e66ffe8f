"""The API's enum values by their short names, as people read and type them.

v1 prefixes every value with its enum's name (``JOB_STATE_RUNNING``, ``LOSS_MSE``) so that the
values of different enums never collide in the languages that put them in one namespace. People
read and type the rest ("RUNNING", "mse"): these functions map between the two.
"""

from __future__ import annotations

from google.protobuf.internal.enum_type_wrapper import EnumTypeWrapper


def prefix(enum: EnumTypeWrapper) -> str:
    """"JOB_STATE_" for JobState: its zero value is always <PREFIX>UNSPECIFIED."""
    return enum.DESCRIPTOR.values[0].name.removesuffix("UNSPECIFIED")


def short_name(enum: EnumTypeWrapper, value: int) -> str:
    """"RUNNING" for JOB_STATE_RUNNING; the number itself for a value this copy lacks (a
    newer daemon's)."""
    try:
        return enum.Name(value).removeprefix(prefix(enum))
    except ValueError:
        return str(value)


def short_names(enum: EnumTypeWrapper) -> list[str]:
    """Every value's short name but UNSPECIFIED, lower case: the choices a user types."""
    return [n.removeprefix(prefix(enum)).lower() for n in enum.keys()
            if not n.endswith("_UNSPECIFIED")]


def parse(enum: EnumTypeWrapper, text: str) -> int:
    """The value named "running", "RUNNING" or "JOB_STATE_RUNNING"; ValueError naming the
    choices otherwise."""
    name = text.strip().upper()
    for candidate in (name, prefix(enum) + name):
        if candidate in enum.keys() and not candidate.endswith("_UNSPECIFIED"):
            return enum.Value(candidate)
    raise ValueError(f"unknown {enum.DESCRIPTOR.name} '{text}': expected one of "
                     + ", ".join(short_names(enum)))

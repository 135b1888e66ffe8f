"""Checks every request gets before its handler runs: text fields of a sane length without NUL
bytes, and enum fields holding a value the API defines.

Protobuf lets a client send any int32 in an enum field and any string in a text field; a NUL
byte then reaches a file name (an ``embedded null byte`` deep in a worker), a 300-character
name a database row, and ``schedule: 99`` a job that silently runs with some default. Walking
the request once, by field, refuses all of them with INVALID_ARGUMENT naming the field.
"""

from __future__ import annotations

from google.protobuf.descriptor import FieldDescriptor
from google.protobuf.message import Message

from ..errors import InvalidArgument

# The longest value of a text field, by field name; any other text field may hold MAX_TEXT.
# Names and ids are identifiers (ours are under 80 characters); paths and keys name files and
# parameters; page tokens are offsets.
MAX_LENGTH = {
    "name": 128, "scene": 128, "initial_from_job": 128, "blob": 128, "initial_blob": 128,
    "request_id": 128, "display_name": 256, "page_token": 32, "sha256": 64,
    "path": 1024, "main_file": 1024, "filename": 1024, "key": 1024,
}
MAX_TEXT = 4096
MAX_OVERRIDE_NAME = 128  # the key of an ``overrides`` entry: an XML <default> name


def check(request: Message) -> None:
    """Raises InvalidArgument for the first text or enum field that is out of bounds."""
    _walk(request, "")


def _walk(message: Message, prefix: str) -> None:
    for fd, value in message.ListFields():
        path = prefix + fd.name
        if fd.type == FieldDescriptor.TYPE_MESSAGE:
            if fd.message_type.GetOptions().map_entry:
                _map(fd, value, path)
            elif _repeated(fd):
                for i, item in enumerate(value):
                    _walk(item, f"{path}[{i}].")
            else:
                _walk(value, path + ".")
            continue
        if fd.type not in (FieldDescriptor.TYPE_STRING, FieldDescriptor.TYPE_ENUM):
            continue  # numbers and bytes: any value is for the handler to judge
        for i, item in enumerate(value) if _repeated(fd) else [(None, value)]:
            where = path if i is None else f"{path}[{i}]"
            if fd.type == FieldDescriptor.TYPE_STRING:
                _text(item, where, MAX_LENGTH.get(fd.name, MAX_TEXT))
            elif fd.type == FieldDescriptor.TYPE_ENUM:
                _enum(fd, item, where)


def _repeated(fd: FieldDescriptor) -> bool:
    # protobuf 7 dropped ``label``; 5.x has no ``is_repeated`` before 5.29.
    if hasattr(fd, "is_repeated"):
        return fd.is_repeated
    return fd.label == FieldDescriptor.LABEL_REPEATED


def _map(fd: FieldDescriptor, value, path: str) -> None:
    key_fd, value_fd = (fd.message_type.fields_by_name[n] for n in ("key", "value"))
    for key in value:
        if key_fd.type == FieldDescriptor.TYPE_STRING:
            _text(key, f"a key of {path}", MAX_OVERRIDE_NAME)
        item = value[key]
        where = f"{path}[{key!r}]"
        if value_fd.type == FieldDescriptor.TYPE_STRING:
            _text(item, where, MAX_TEXT)
        elif value_fd.type == FieldDescriptor.TYPE_MESSAGE:
            _walk(item, where + ".")


def _text(value: str, where: str, limit: int) -> None:
    if "\0" in value:
        shown = value.replace("\0", "\\0")
        raise InvalidArgument(f"{where} contains a NUL byte: '{shown[:80]}"
                              f"{'...' if len(shown) > 80 else ''}'")
    if len(value) > limit:
        raise InvalidArgument(f"{where} is {len(value):,} characters long; at most {limit:,} "
                              f"are allowed: '{value[:40]}...'")


def _enum(fd: FieldDescriptor, value: int, where: str) -> None:
    enum = fd.enum_type
    if value not in enum.values_by_number:
        known = ", ".join(f"{v.name} ({v.number})" for v in enum.values if v.number)
        raise InvalidArgument(f"{where} {value} is not a {enum.name}: expected one of {known}")

"""Mesh files checked before a renderer reads them.

Mitsuba 3.9's PLY reader takes face indices as they are: an index past the vertices makes it
read memory it does not own, which renders garbage (1000 with 4 vertices) or ends the process
with SIGSEGV (2^31 - 1). Its OBJ reader checks indices itself but not as a user would read it
(a relative index such as -1 wraps around to 4294967295). So every PLY and OBJ a scene uses is
read here first, as Mitsuba would read it, and refused with the first bad face named.
"""

from __future__ import annotations

import re
from typing import Callable

import numpy as np


class MeshError(ValueError):
    """A mesh Mitsuba must not read; the message names the file and the face."""


# PLY property types Mitsuba 3.9 reads (src/shapes/ply.h), as numpy type codes.
_PLY_TYPES = {"char": "i1", "uchar": "u1", "short": "i2", "ushort": "u2", "int": "i4",
              "uint": "u4", "float": "f4", "double": "f8", "uint8": "u1", "uint16": "u2",
              "uint32": "u4", "int8": "i1", "int16": "i2", "int32": "i4", "long": "i8",
              "ulong": "u8", "half": "f2", "float16": "f2", "float32": "f4", "float64": "f8"}
_FORMATS = {"ascii": "", "binary_little_endian": "<", "binary_big_endian": ">"}
_INTEGER = re.compile(rb"[+-]?\d+")
# A number an ASCII PLY may hold: one that C++ stream extraction reads whole. Anything else
# could be read as two numbers there and shift every later value against what is checked here.
_ASCII_BODY = re.compile(rb"\s*(?:[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?"
                         rb"(?:\s+[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?)*)?\s*")
_LIMIT = 1 << 32  # Mitsuba keeps counts and indices as 32-bit unsigned integers


class _Element:
    def __init__(self, name: str, count: int) -> None:
        self.name, self.count = name, count
        self.fields: list[str] = []   # numpy type code of each value of a record
        self.lists: list[int] = []    # index of each list's count field in ``fields``


def check_ply(data: bytes, name: str) -> None:
    """Refuses a PLY whose faces index past its vertices (any integer or float index type,
    ASCII and binary of either byte order), or that Mitsuba would read differently."""
    elements, order, start = _ply_header(data, name)
    vertices = next((e.count for e in reversed(elements) if e.name == "vertex"), 0)
    if order:
        offset = start
        for element in elements:
            dtype = np.dtype([(f"f{i}", order + t) for i, t in enumerate(element.fields)])
            end = offset + element.count * dtype.itemsize
            if end > len(data):
                raise MeshError(f"'{name}' ends inside its '{element.name}' element (it declares "
                                f"{element.count} of them)")
            if element.name == "face":
                rows = np.frombuffer(data, dtype, element.count, offset)
                _check_faces(element, [rows[f"f{i}"] for i in range(len(element.fields))],
                             vertices, name)
            offset = end
        return
    body = data[start:]
    if not _ASCII_BODY.fullmatch(body):
        raise MeshError(f"'{name}' holds something other than plain numbers after its header: "
                        "Mitsuba's ASCII PLY reader would read its values differently")
    tokens = body.split()
    offset = 0
    for element in elements:
        width = len(element.fields)
        end = offset + element.count * width
        if end > len(tokens):
            raise MeshError(f"'{name}' ends inside its '{element.name}' element (it declares "
                            f"{element.count} of them)")
        block = np.array(tokens[offset:end], dtype=object).reshape(element.count, width)
        for i, kind in enumerate(element.fields):
            if kind[0] in "iu":
                bad = [t for t in block[:, i] if not _INTEGER.fullmatch(t)]
                if bad:
                    raise MeshError(f"'{name}': '{bad[0].decode()}' in element "
                                    f"'{element.name}' is not an integer, as its type says")
        if element.name == "face":
            # As float64: exact for every index Mitsuba could use (below 2^32).
            _check_faces(element, [block[:, i].astype(np.float64) for i in range(width)],
                         vertices, name)
        offset = end


def _ply_header(data: bytes, name: str) -> tuple[list[_Element], str | None, int]:
    """The elements, the byte order ('' for ASCII, None before 'format') and where the data
    starts, following Mitsuba's header rules."""
    elements: list[_Element] = []
    order: str | None = None
    position = 0
    while True:
        newline = data.find(b"\n", position)
        if newline < 0:
            raise MeshError(f"'{name}' is not a PLY file Mitsuba reads: no 'end_header'")
        words = data[position:newline].decode("latin-1").split()
        position = newline + 1
        if not words or words[0] in ("comment", "obj_info", "ply"):
            continue
        if words[0] == "format" and len(words) == 3 and words[1] in _FORMATS:
            order = _FORMATS[words[1]]
        elif words[0] == "element" and len(words) == 3 and words[2].isdigit():
            if int(words[2]) >= _LIMIT:
                raise MeshError(f"'{name}' declares {words[2]} '{words[1]}' records: Mitsuba "
                                f"counts them in 32 bits")
            elements.append(_Element(words[1], int(words[2])))
        elif words[0] == "property" and elements and len(words) == 3 and words[1] in _PLY_TYPES:
            elements[-1].fields.append(_PLY_TYPES[words[1]])
        elif (words[0] == "property" and elements and len(words) == 5 and words[1] == "list"
              and words[2] in _PLY_TYPES and words[3] in _PLY_TYPES):
            # Mitsuba reads a list as its count (which must be 3) and three items.
            elements[-1].lists.append(len(elements[-1].fields))
            elements[-1].fields += [_PLY_TYPES[words[2]]] + [_PLY_TYPES[words[3]]] * 3
        elif words == ["end_header"]:
            break
        else:
            raise MeshError(f"'{name}' is not a PLY file Mitsuba reads: header line "
                            f"'{' '.join(words)}'")
    if order is None:
        raise MeshError(f"'{name}' is not a PLY file Mitsuba reads: no 'format' line")
    return elements, order, position


def _check_faces(element: _Element, columns: list[np.ndarray], vertices: int,
                 name: str) -> None:
    """Mitsuba takes a face's corners from the first list of the element and requires every
    list to hold 3 items."""
    if not element.lists:
        raise MeshError(f"'{name}': its 'face' element has no vertex index list")
    for at in element.lists:
        wrong = np.flatnonzero(columns[at] != 3)
        if wrong.size:
            raise MeshError(f"'{name}': face {wrong[0]} has {_number(columns[at][wrong[0]])} "
                            "corners; Mitsuba reads triangles only")
    first = element.lists[0]
    corners = np.stack([np.asarray(columns[first + k]) for k in (1, 2, 3)], axis=1)
    if corners.dtype.kind == "f":
        valid = (corners >= 0) & (corners < vertices) & (np.floor(corners) == corners)
    else:
        valid = (corners >= 0) & (corners < vertices)
    bad = np.flatnonzero(~valid.all(axis=1))
    if bad.size:
        face = int(bad[0])
        index = _number(corners[face][~valid[face]][0])
        have = (f"{vertices} vertices (indices 0 to {vertices - 1})" if vertices
                else "no vertices")
        raise MeshError(f"'{name}': face {face} refers to vertex {index}, but the file has "
                        f"{have}")


def _number(value) -> int | float:
    return int(value) if float(value).is_integer() else float(value)


def check_obj(data: bytes, name: str) -> None:
    """Refuses an OBJ face whose vertex index (1-based) is not among the vertices defined
    before it. Mitsuba 3.9 reads no relative (negative) indices: those are refused too, with
    the reason."""
    vertices = 0
    for number, line in enumerate(data.split(b"\n"), 1):
        line = line.lstrip(b" \t\r")
        head = line[:2]
        if head in (b"v ", b"v\t"):
            vertices += 1
        elif head in (b"f ", b"f\t"):
            for corner in line[2:].split():
                index = _INTEGER.match(corner)
                if index is None:
                    break  # Mitsuba stops reading the face here
                value = int(index.group())
                if value < 0:
                    raise MeshError(f"'{name}' line {number}: face uses the relative vertex "
                                    f"index {value}, which Mitsuba 3.9 does not read; write "
                                    "absolute (1-based) indices")
                if not 1 <= value <= vertices:
                    raise MeshError(f"'{name}' line {number}: face refers to vertex {value}, "
                                    f"but {vertices} vertices are defined before it")


CHECKS: dict[str, Callable[[bytes, str], None]] = {"ply": check_ply, "obj": check_obj}

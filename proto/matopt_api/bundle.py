"""Scene bundles: a main XML plus the files it references, addressed by '/'-separated paths.

Both sides follow these rules: the client to find which files to upload, the daemon to refuse a
bundle that is incomplete or that points outside itself. Mitsuba resolves a relative
``filename`` against the directory of the main XML, so we do the same.
"""

from __future__ import annotations

import posixpath
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass

_DRIVE = re.compile(r"^[A-Za-z]:")
_DEFAULT_REF = re.compile(r"\$(\w+)")
# Names the daemon gives the files it writes next to a bundle's (the prepared scene XML).
RESERVED_PREFIX = ".matopt-"


class BundleError(ValueError):
    """A bundle or scene file that cannot be used as it is; the message names the culprit."""


def normalize(path: str, *, origin: str = "") -> str:
    """Canonical bundle path: '/' separators, no '.', no '..' that leaves the bundle.

    ``origin`` names where the path came from, for the error message.
    """
    where = f" (in {origin})" if origin else ""
    p = path.replace("\\", "/")
    if p.startswith("/") or _DRIVE.match(p):
        raise BundleError(f"absolute path '{path}'{where} is not allowed in a scene bundle")
    parts: list[str] = []
    for part in p.split("/"):
        if part in ("", "."):
            continue
        if part == "..":
            if not parts:
                raise BundleError(f"path '{path}'{where} leaves the scene bundle")
            parts.pop()
        elif part.startswith(RESERVED_PREFIX):
            raise BundleError(f"path '{path}'{where} uses the reserved name prefix "
                              f"'{RESERVED_PREFIX}': rename the file")
        else:
            parts.append(part)
    if not parts:
        raise BundleError(f"empty path '{path}'{where}")
    return "/".join(parts)


@dataclass(frozen=True)
class Reference:
    """A file that a scene XML refers to."""

    xml: str       # bundle path of the XML that names it
    written: str   # as written in the XML (after $default substitution)
    path: str      # bundle path it resolves to


def parse_xml(text: bytes | str, name: str) -> ET.Element:
    """Parses a scene XML, turning a syntax error into a message that names the file and line."""
    try:
        return ET.fromstring(text)
    except ET.ParseError as exc:
        raise BundleError(f"malformed XML in '{name}': {exc}") from None


def declared_defaults(root: ET.Element) -> dict[str, str]:
    """The ``<default name=... value=...>`` parameters a scene declares."""
    return {e.get("name", ""): e.get("value", "") for e in root.iter("default") if e.get("name")}


def references(xml_path: str, text: bytes | str, overrides: dict[str, str] | None = None,
               base: str | None = None) -> list[Reference]:
    """Every file named by ``<string name="filename">`` or ``<include filename>`` in one XML.

    Paths resolve against ``base``, the main XML's folder: Mitsuba 3.9 resolves a filename in
    an included XML against the main file's folder too, not the included file's.

    ``$name`` placeholders are substituted with the XML's defaults and the given overrides, as
    Mitsuba does, so that ``<string name="filename" value="$mesh"/>`` resolves too.
    """
    xml_path = normalize(xml_path)
    root = parse_xml(text, xml_path)
    values = {**declared_defaults(root), **(overrides or {})}
    base = posixpath.dirname(xml_path) if base is None else base
    found: list[Reference] = []
    for elem in root.iter():
        if elem.tag == "string" and elem.get("name") == "filename":
            raw = elem.get("value", "")
        elif elem.tag == "include":
            raw = elem.get("filename", "")
        else:
            continue
        written = _DEFAULT_REF.sub(lambda m: values.get(m.group(1), m.group(0)), raw)
        origin = f"'{xml_path}'"
        path = normalize(posixpath.join(base, written.replace("\\", "/")), origin=origin)
        if written.replace("\\", "/").startswith("/") or _DRIVE.match(written):
            raise BundleError(f"absolute path '{written}' (in {origin}) is not allowed in a scene bundle")
        found.append(Reference(xml_path, written, path))
    return found


def closure(main: str, read, overrides: dict[str, str] | None = None
            ) -> dict[str, list[Reference]]:
    """Follows ``<include>`` files from the main XML; returns each XML's references.

    ``read(path) -> bytes | None`` gives a bundle file's content (None when missing).
    ``overrides`` are the XML defaults the scene is loaded with, since ``$name`` in a filename
    may then name a different file than the XML's own default.
    """
    main = normalize(main)
    todo, seen, base = [main], {}, posixpath.dirname(main)
    while todo:
        xml = todo.pop()
        if xml in seen:
            continue
        text = read(xml)
        if text is None:
            raise BundleError(f"scene file '{xml}' is missing from the bundle")
        seen[xml] = references(xml, text, overrides, base)
        todo += [r.path for r in seen[xml] if r.path.lower().endswith(".xml")]
    return seen

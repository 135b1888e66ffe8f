"""Scene bundles: a main XML plus the files it references, addressed by '/'-separated paths.

Both sides follow these rules: the client to find which files to upload, the daemon to refuse a
bundle that is incomplete or that points outside itself. A scene must not reach any file
outside its bundle, so the rules follow Mitsuba 3.9's parser (src/core/parser.cpp) and plugins
exactly. Files are named by:

- ``<include filename>``: parsed at once, looked up in the including file's folder first,
  then in the folders of the files that included that one, then in the main XML's folder;
- a ``filename`` attribute (``<spectrum name=... filename=...>``): read at once, looked up in
  the folders of the files that included the current one, then in the main XML's folder;
- ``<string name="filename">`` of any plugin (meshes, bitmaps, environment maps, volumes,
  measured BSDFs, curves): opened when the plugin is built, from the main XML's folder;
- after these, every file name is also looked up from the bundle's root, which stands for the
  directory Mitsuba was started in (its file resolver holds the current directory): scenes
  written to be run from a project's root name files relative to it;
- ``<string name="material">`` of conductors: ``data/ior/<material>.eta.spd`` from the same
  folders as Mitsuba's own data;
- the ``type`` of every object: Mitsuba loads ``plugins/<type>.so`` through the same lookup,
  as code (so types are plain names, and a bundle holds no ``.so`` file);
- ``<path value>``: adds a folder to the lookup for the rest of the load. Refused.

File names may separate folders with ``\\`` (scenes written on Windows): it is read as
``/`` in every XML, also where a ``$name`` brings it in. Mitsuba on Linux would take it as part
of a name, so the daemon hands Mitsuba every XML with its file names written out as read here.

``$name`` in any attribute is first replaced by a parameter (the overrides a scene is loaded
with, then ``<default>`` declarations in the order Mitsuba reads them). Where Mitsuba's result
could depend on the order of its replacements, the bundle is refused rather than guessed at.

The XML itself is read by Mitsuba with pugixml, which ignores DOCTYPEs and entities and knows
no namespaces or encodings other than UTF-8 and Latin-1; files using any of them would read
differently here, so they are refused. So are files nested too deeply: Mitsuba's parser
recurses once per level and a deep file ends the process.
"""

from __future__ import annotations

import posixpath
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from typing import Callable
from xml.parsers import expat

_DRIVE = re.compile(r"^[A-Za-z]:")
_IDENTIFIER = re.compile(r"[A-Za-z0-9_]+")
_RUN = re.compile(r"[A-Za-z0-9_]*")
_MATERIAL = re.compile(r"[A-Za-z0-9_-]+")
_DECLARED_ENCODING = re.compile(rb"^\s*<\?xml[^>]*?encoding\s*=\s*[\"']([^\"']*)[\"']")
_UTF8_NAMES = {"utf-8", "utf8", "us-ascii", "ascii"}
_FOREIGN_BOMS = (b"\xff\xfe", b"\xfe\xff", b"\x00\x00\xfe\xff")

# Names the daemon gives the files it writes next to a bundle's (the prepared scene XML).
RESERVED_PREFIX = ".matopt-"
# Mitsuba's parser recurses once per element level and once more per include; 20,000 levels in
# an included file ended the renderer with SIGSEGV. Real scenes stay under 10.
MAX_DEPTH = 100
MAX_INCLUDE_DEPTH = 15   # Mitsuba's own limit (ParserConfig::max_include_depth)
MAX_INCLUDES = 1000      # includes read in all, counting a file each time it is included
# The bundle's root folder, tried last for every file name: it stands for the directory
# Mitsuba was started in, which its file resolver holds.
ROOT = ""


class BundleError(ValueError):
    """A bundle or scene file that cannot be used as it is; the message names the culprit."""


class _Outside(BundleError):
    """A path whose '..' leads out of the bundle."""


class _Unclear(BundleError):
    """A ``$`` substitution whose result Mitsuba might compute differently."""


# A bundle is laid out as files under a folder of the daemon's (and its workers'): each
# name must fit a file system's limit (255 bytes on Linux, macOS and Windows alike), and the
# whole path well within PATH_MAX (4096) once under that folder.
MAX_NAME_BYTES = 255
MAX_PATH_BYTES = 1024


def normalize(path: str, *, origin: str = "") -> str:
    """Canonical bundle path: '/' separators, no '.', no '..' that leaves the bundle.

    ``origin`` names where the path came from, for the error message.
    """
    where = f" (in {origin})" if origin else ""
    if "\x00" in path:
        raise BundleError(f"path {path!r}{where} holds a NUL character")
    p = path.replace("\\", "/")
    if p.startswith("/") or _DRIVE.match(p):
        raise BundleError(f"absolute path '{path}'{where} is not allowed in a scene bundle")
    parts: list[str] = []
    for part in p.split("/"):
        if part in ("", "."):
            continue
        if part == "..":
            if not parts:
                raise _Outside(f"path '{path}'{where} leaves the scene bundle")
            parts.pop()
        elif part.startswith(RESERVED_PREFIX):
            raise BundleError(f"path '{path}'{where} uses the reserved name prefix "
                              f"'{RESERVED_PREFIX}': rename the file")
        else:
            parts.append(part)
    if not parts:
        raise BundleError(f"empty path '{path}'{where}")
    for part in parts:
        if len(part.encode()) > MAX_NAME_BYTES:
            raise BundleError(f"path '{path}'{where} has a file or folder name of "
                              f"{len(part.encode())} bytes: file systems take at most "
                              f"{MAX_NAME_BYTES}; rename it")
    if len("/".join(parts).encode()) > MAX_PATH_BYTES:
        raise BundleError(f"path '{path}'{where} is {len('/'.join(parts).encode())} bytes "
                          f"long: a bundle path may have at most {MAX_PATH_BYTES}")
    if parts[-1].endswith(".so"):
        raise BundleError(f"'{path}'{where} is a shared library: Mitsuba loads a "
                          "'plugins/<type>.so' it finds beside a scene as renderer code, so "
                          "a scene bundle holds none")
    return "/".join(parts)


@dataclass(frozen=True)
class Reference:
    """A file that a scene XML refers to."""

    xml: str       # bundle path of the XML that names it
    written: str   # as written in the XML (after $default substitution)
    path: str      # bundle path it resolves to (where it was first expected, if missing)
    plugin: str = ""  # what reads it: the enclosing object's type, "include" or "spectrum"
    tried: tuple[str, ...] = ()  # bundle paths looked at, in Mitsuba's order


def parse_xml(text: bytes | str, name: str) -> ET.Element:
    """Parses a scene XML, refusing what Mitsuba would read differently or not survive; a
    syntax error becomes a message that names the file and line."""
    data = text.encode() if isinstance(text, str) else text
    if data.startswith(_FOREIGN_BOMS) or b"\x00" in data:
        raise BundleError(f"'{name}' is not UTF-8 text: Mitsuba reads scene files as UTF-8")
    try:
        data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise BundleError(f"'{name}' is not UTF-8 text (byte {exc.start}): Mitsuba reads "
                          "scene files as UTF-8") from None
    declared = _DECLARED_ENCODING.match(data.removeprefix(b"\xef\xbb\xbf"))
    if declared and declared.group(1).decode().lower() not in _UTF8_NAMES:
        raise BundleError(f"'{name}' declares encoding '{declared.group(1).decode()}': Mitsuba "
                          "reads scene files as UTF-8; save it as UTF-8")
    _screen(data, name)
    try:
        return ET.fromstring(data)
    except ET.ParseError as exc:
        raise BundleError(f"malformed XML in '{name}': {exc}") from None


def _screen(data: bytes, name: str) -> None:
    """One pass of expat over the file before any tree is built: nesting depth, DOCTYPE
    (entity expansion, external entities) and namespaces."""
    parser = expat.ParserCreate()
    depth = 0

    def start(tag: str, attrs: dict[str, str]) -> None:
        nonlocal depth
        depth += 1
        line = parser.CurrentLineNumber
        if depth > MAX_DEPTH:
            raise BundleError(f"'{name}' nests elements more than {MAX_DEPTH} levels deep "
                              f"(line {line}): Mitsuba's parser does not survive deep "
                              f"nesting, so scene files are limited to {MAX_DEPTH} levels")
        if ":" in tag or any(":" in a or a == "xmlns" for a in attrs):
            raise BundleError(f"'{name}' uses an XML namespace (<{tag}>, line {line}): "
                              "Mitsuba scene files use none")

    def end(tag: str) -> None:
        nonlocal depth
        depth -= 1

    def doctype(*_) -> None:
        raise BundleError(f"'{name}' has a DOCTYPE (line {parser.CurrentLineNumber}): entity "
                          "declarations are not allowed in scene files")

    parser.StartElementHandler, parser.EndElementHandler = start, end
    parser.StartDoctypeDeclHandler = doctype
    try:
        parser.Parse(data, True)
    except expat.ExpatError as exc:
        raise BundleError(f"malformed XML in '{name}': {exc}") from None


def declared_defaults(root: ET.Element) -> dict[str, str]:
    """The ``<default name=... value=...>`` parameters a scene declares."""
    return {e.get("name", ""): e.get("value", "") for e in root.iter("default") if e.get("name")}


def _names_file(elem: ET.Element, attr: str) -> bool:
    """Whether the attribute holds a file name as written (before any ``$`` substitution):
    there a ``\\`` separates folders."""
    return attr == "filename" or (attr == "value" and elem.tag == "string"
                                  and elem.get("name") == "filename")


def substitute(value: str, params: dict[str, str | None], where: str) -> str:
    """``value`` with ``$name`` replaced as Mitsuba 3.9 does (``\\$`` stays a literal '$').

    Mitsuba replaces each parameter in turn, longest name first, as a plain substring: a name
    followed by more letters is replaced all the same (``$mesh_lo`` with only ``mesh`` declared
    becomes the value of ``mesh`` then ``_lo``). That is computed exactly here. Two references
    side by side (``$a$b``), or a parameter whose value holds a '$' (None in ``params``), could
    be resolved in another order by Mitsuba: those raise ``_Unclear``.
    """
    out: list[str] = []
    i = 0
    while (j := value.find("$", i)) >= 0:
        if j > 0 and value[j - 1] == "\\":
            out += [value[i:j - 1], "$"]
            i = j + 1
            continue
        out.append(value[i:j])
        run = _RUN.match(value, j + 1).group()
        end = j + 1 + len(run)
        if end < len(value) and value[end] == "$" or not run:
            raise _Unclear(f"{where}: '{value}' has a '$' that Mitsuba may read in more than "
                           "one way; separate parameters, or write '\\$' for a literal '$'")
        name = next((run[:k] for k in range(len(run), 0, -1) if run[:k] in params), None)
        if name is None:
            raise BundleError(f"{where}: '${run}' in '{value}' names no parameter (declare it "
                              "with <default> before it is used, or pass it as an override)")
        if params[name] is None:
            raise _Unclear(f"{where}: parameter '{name}' used in '{value}' has a value with a "
                           "'$', which Mitsuba may substitute again")
        out.append(params[name] + run[len(name):])
        i = end
    out.append(value[i:])
    return "".join(out)


@dataclass
class _File:
    """An XML being walked: its elements still to visit, and the lookup folders its parse
    sees (those of the files that included it, innermost first)."""

    xml: str
    todo: list[tuple[ET.Element, int, str]]  # element, depth (counting includes), owner type
    folders: list[str]
    chain: tuple[str, ...]


def closure(main: str, read: Callable[[str], bytes | str | None],
            overrides: dict[str, str] | None = None,
            exists: Callable[[str], bool] | None = None,
            rewrite: dict[str, ET.Element] | None = None) -> dict[str, list[Reference]]:
    """Reads the scene as Mitsuba will, from the main XML through every ``<include>``, and
    returns each XML's file references.

    ``read(path)`` gives a bundle file's content (None when missing); ``exists(path)`` says
    whether it is there without reading it (default: ``read``). ``overrides`` are the XML
    defaults the scene is loaded with: ``$name`` in a filename may then name a different file
    than the XML's own default. As on the daemon, only overrides the main XML declares apply.

    With ``rewrite``, every XML read is left in it (a tree already there, the main XML's, is
    used instead of reading the file) with each file name written out as resolved here: '/'
    separators and no ``$``. Mitsuba then opens the files these rules name. It is to be loaded
    with these ``overrides``, which its ``<default>``s then refer to (see
    ``_overrides_referred``).

    Raises ``BundleError`` for a file reference that leaves the bundle and anything Mitsuba
    would read differently from these rules. A reference to a missing file is returned (at the
    path it was first expected, with the places ``tried``): the caller says which, and must
    refuse the scene. After a missing ``<include>`` the walk goes on without it, until the end
    or the first error, which may be due to the missing file: then what was found is returned.
    """
    main = normalize(main)
    exists = exists or (lambda p: read(p) is not None)
    trees = rewrite if rewrite is not None else {}  # each file parsed once, walked each time
    if main not in trees:
        trees[main] = _read_xml(main, read, f"main file '{main}'")
    root = trees[main]
    declared = declared_defaults(root)
    params: dict[str, str | None] = {
        k: (None if "$" in v else v) for k, v in (overrides or {}).items() if k in declared}
    scene_dir = posixpath.dirname(main)
    found: dict[str, list[Reference]] = {}
    missing_include = False
    stack = [_File(main, [(root, 1, "")], [], (main,))]
    includes = 0
    try:
        while stack:
            current = stack[-1]
            if not current.todo:
                stack.pop()
                continue
            elem, depth, owner = current.todo.pop()
            xml = current.xml
            where = f"'{xml}', <{elem.tag}>"
            if depth > MAX_DEPTH:
                raise BundleError(f"'{xml}' nests elements more than {MAX_DEPTH} levels deep, "
                                  "counting the elements around its <include>: Mitsuba's "
                                  f"parser does not survive deep nesting, so scenes are limited "
                                  f"to {MAX_DEPTH} levels")

            def attr(name: str) -> str | None:
                raw = elem.get(name)
                if raw is None:
                    return None
                if _names_file(elem, name):
                    raw = raw.replace("\\", "/")
                return substitute(raw, params, f"{where} {name}")

            def refer(name: str, folders: list[str], plugin: str) -> Reference:
                # A '\' brought in by a parameter separates folders all the same.
                value = attr(name) or ""
                effective = value.replace("\\", "/")
                raw = elem.get(name, "")
                written = value if "$" in raw else raw  # for messages: as the user wrote it
                if "$" in effective:  # written out, Mitsuba would substitute it once more
                    raise BundleError(f"{where}: file name '{written}' has a '$': rename the "
                                      "file")
                path, tried = _lookup(xml, effective, written, [*folders, ROOT], exists)
                if rewrite is not None:
                    elem.set(name, effective)
                found.setdefault(xml, []).append(Reference(xml, written, path, plugin, tried))
                return found[xml][-1]

            if elem.tag == "path":
                raise BundleError(f"'{xml}' has a <path> element: it adds a folder to Mitsuba's "
                                  "file lookup for the rest of the load, so a file of the "
                                  "bundle could be replaced by one from outside it; bundles may "
                                  "not use it")
            if elem.tag == "default":
                _declare(elem, params, where)
            kind = attr("type")
            if kind is not None and not _IDENTIFIER.fullmatch(kind):
                raise BundleError(f"{where} has type '{kind}': Mitsuba loads 'plugins/<type>.so' "
                                  "as code, so a type is letters, digits and '_' only")
            owner = kind or owner
            if elem.tag == "string":
                name = attr("name")
                if name == "filename":
                    refer("value", [scene_dir], owner)
                elif name == "material":
                    material = attr("value") or ""
                    if not _MATERIAL.fullmatch(material):
                        raise BundleError(f"{where} names material '{material}': Mitsuba reads "
                                          "'data/ior/<material>.eta.spd', so a material is "
                                          "letters, digits, '_' and '-' only")
            has_filename = elem.get("filename") is not None
            if has_filename and elem.tag == "include":
                includes += 1
                ref = refer("filename", [posixpath.dirname(xml), *current.folders, scene_dir],
                            "include")
                if ref.path in current.chain:
                    raise BundleError(f"'{xml}' includes '{ref.written}', which includes it in "
                                      f"turn ({' -> '.join(current.chain + (ref.path,))})")
                if len(current.chain) >= MAX_INCLUDE_DEPTH:
                    raise BundleError(f"'{xml}' includes '{ref.written}': includes nest more "
                                      f"than {MAX_INCLUDE_DEPTH} files deep, Mitsuba's limit")
                if includes > MAX_INCLUDES:
                    raise BundleError(f"'{xml}' includes '{ref.written}': the scene reads more "
                                      f"than {MAX_INCLUDES} included files, counting each time "
                                      "a file is included")
                if not exists(ref.path):
                    missing_include = True
                    continue
                if ref.path not in trees:
                    trees[ref.path] = _read_xml(ref.path, read,
                                                f"'{ref.written}', included by '{xml}',")
                stack.append(_File(ref.path, [(trees[ref.path], depth + 1, "")],
                                   [posixpath.dirname(xml), *current.folders],
                                   current.chain + (ref.path,)))
                continue
            if has_filename:
                refer("filename", [*current.folders, scene_dir], elem.tag)
            current.todo.extend((child, depth + 1, owner) for child in reversed(elem))
    except BundleError:
        if not missing_include:
            raise
    if rewrite is not None:
        _overrides_referred(root, {k for k, v in params.items()
                                   if v is not None and k in (overrides or {})})
    return found


def _overrides_referred(root: ET.Element, names: set[str]) -> None:
    """Sets each named parameter's ``<default>`` to ``$name``.

    Mitsuba refuses a parameter it is passed but never substitutes ("Found unused
    parameters"), and a file name written out no longer says ``$name``: an override naming
    a file (``--set grid=start.vol``) would be refused. Its own ``<default>`` now refers to
    it: Mitsuba substitutes the override there, then skips the declaration, as for any name
    it was passed.
    """
    for elem in root.iter("default"):
        name = elem.get("name")
        if name in names:
            elem.set("value", f"${name}")
            names.discard(name)  # only the first declaration counts


def _read_xml(path: str, read: Callable[[str], bytes | str | None], what: str) -> ET.Element:
    text = read(path)
    if text is None:
        raise BundleError(f"{what} is not in the bundle (expected at '{path}')")
    return parse_xml(text, path)


def _declare(elem: ET.Element, params: dict[str, str | None], where: str) -> None:
    """A ``<default>``: the first declaration of a name counts, as in Mitsuba; its value is
    substituted with the parameters known at that point."""
    name = substitute(elem.get("name", ""), params, f"{where} name")
    if not _IDENTIFIER.fullmatch(name):
        raise BundleError(f"{where} declares parameter '{name}': parameter names are "
                          "letters, digits and '_' only")
    if name in params:
        return
    try:
        value = substitute(elem.get("value", ""), params, f"{where} value")
    except _Unclear:
        value = None
    params[name] = None if value is None or "$" in value else value


def _lookup(xml: str, effective: str, written: str, folders: list[str],
            exists: Callable[[str], bool]) -> tuple[str, tuple[str, ...]]:
    """The bundle path where Mitsuba finds ``effective``, trying ``folders`` in order as its
    file resolver does (the first one holding the file), and the paths tried. Mitsuba looks in
    every folder before the one holding the file, so none of those may lead outside the
    bundle. A file found nowhere resolves to where it was first expected; where every folder
    leads outside, that is the error. Messages quote ``written``."""
    origin = f"'{xml}'"
    if effective.startswith("/") or _DRIVE.match(effective):
        raise BundleError(f"absolute path '{written}' (in {origin}) is not allowed in a scene "
                          "bundle")
    tried: list[str] = []
    outside: BundleError | None = None
    for folder in dict.fromkeys(folders):
        joined = posixpath.join(folder, effective)
        try:
            tried.append(normalize(joined, origin=origin))
        except _Outside:
            outside = outside or BundleError(f"path '{written}' (in {origin}) leaves the "
                                             "scene bundle")
            continue
        except BundleError as exc:
            raise BundleError(str(exc).replace(f"'{joined}'", f"'{written}'")) from None
        if exists(tried[-1]):
            if outside:
                raise outside
            return tried[-1], tuple(tried)
    if not tried:
        raise outside or BundleError(f"empty path '{written}' (in {origin})")
    return tried[0], tuple(tried)

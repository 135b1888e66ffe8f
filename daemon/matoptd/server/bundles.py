"""Turning an uploaded bundle into what a worker loads, without importing Mitsuba.

What happens here, all before a worker sees the scene:
- every file the XML refers to must be in the bundle and inside it (``matopt_api.bundle`` has
  the path rules), and every file of the bundle must have been uploaded by the caller;
- every PLY and OBJ mesh must index only vertices it has (``meshes``): Mitsuba does not
  check, and an index far past the end ends the renderer;
- objects directly under ``<scene>`` that have no ``id`` get one from their position
  (``shape_3``: the fourth ``<shape>``). Mitsuba would name them after a memory address
  (``object_140092774243456``), so their parameter keys would change on every load and a job
  would lose its parameters after a restart;
- file names are written out as Mitsuba is to open them: Windows ``\\`` separators become
  ``/`` and ``$`` parameters are replaced, in the main XML and in every included one; bitmap
  textures load as float (8-bit ones carry no gradient); removed integrators (``prb_reparam``)
  become their successors;
- ``<default>`` overrides are applied only where the XML declares the default; others are
  reported as warnings, never required.
The result is a prepared copy of the main XML (``.matopt-scene.xml``, a name no bundle file can
take) stored as a blob beside the bundle's, and prepared copies of the included XMLs that
changed, which a worker lays out at their own paths: a worker gets the scene as digests, and
the user's blobs stay as uploaded. A file name is found as Mitsuba run from the bundle's root
would find it (``matopt_api.bundle``): the worker's file resolver holds that root too.
"""

from __future__ import annotations

import posixpath
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

from matopt_api import bundle
from matopt_api.v1 import matopt_pb2 as pb

from ..errors import InvalidArgument, NotFound
from ..store.blobs import Blobs
from . import meshes

CORNELL_BOX = Path(__file__).parent.parent / "engine" / "cornell_box.xml"
CORNELL_NAME = "cornell_box.xml"
LOADABLE_NAME = bundle.RESERVED_PREFIX + "scene.xml"

# Objects whose keys Mitsuba derives from their id when they sit directly under <scene>.
_NAMED_TAGS = ("shape", "bsdf", "emitter", "sensor", "medium", "texture", "volume", "phase")


@dataclass
class PreparedScene:
    xml: bytes                          # the copy of the main XML to hand to Mitsuba
    overrides: dict[str, str]           # the ones the XML declares
    warnings: list[str] = field(default_factory=list)
    # Included XMLs that Mitsuba gets rewritten (file names written out, float textures), by
    # bundle path: a worker lays them out in place of the user's files, which stay as uploaded.
    includes: dict[str, bytes] = field(default_factory=dict)


def check_bundle(blobs: Blobs, main_file: str, files: list[pb.BundleFile],
                 overrides: dict[str, str], owner: str
                 ) -> tuple[str, dict[str, str], PreparedScene]:
    """The main XML's bundle path, every bundle file's digest and the prepared scene, once the
    bundle is complete, is ``owner``'s, stays inside itself (``matopt_api.bundle`` reads it as
    Mitsuba will) and its meshes index only vertices they have."""
    if not main_file:
        raise InvalidArgument("main_file is empty: name the bundle's main scene XML")
    try:
        main = bundle.normalize(main_file, origin="main_file")
        paths: dict[str, str] = {}
        for f in files:
            path = bundle.normalize(f.path, origin="the bundle's file list")
            if path in paths and paths[path] != f.sha256:
                raise InvalidArgument(f"bundle lists '{path}' twice with different contents")
            paths[path] = f.sha256
    except bundle.BundleError as exc:
        raise InvalidArgument(str(exc)) from None
    if main not in paths:
        raise InvalidArgument(f"main_file '{main}' is not among the bundle's files")
    _no_file_as_folder(paths)
    for path, sha in paths.items():
        # Another user's upload is as absent as one never made: nothing is read before this.
        if not blobs.owns(owner, sha):
            raise NotFound(f"bundle file '{path}' (blob 'blobs/{sha}') not found (upload it "
                           "first)")

    def read(path: str) -> bytes | None:
        return blobs.read(paths[path]) if path in paths else None

    root, applied, warnings = _prepared_tree(read(main), main, overrides)
    trees = {main: root}  # every XML, with its file names written out for Mitsuba
    checked: set[tuple[str, str]] = set()
    try:
        found = bundle.closure(main, read, applied, exists=paths.__contains__, rewrite=trees)
        missing = [ref for refs in found.values() for ref in refs if ref.path not in paths]
        if missing:
            raise InvalidArgument(missing_message(missing))
        for refs in found.values():
            for ref in refs:
                if ref.plugin in meshes.CHECKS and (ref.plugin, ref.path) not in checked:
                    meshes.CHECKS[ref.plugin](read(ref.path), ref.path)
                    checked.add((ref.plugin, ref.path))
    except (bundle.BundleError, meshes.MeshError) as exc:
        raise InvalidArgument(str(exc)) from None
    includes = {}
    for path, tree in trees.items():
        float_textures(tree)
        if path != main and _xml(tree) != _xml(bundle.parse_xml(read(path), path)):
            includes[path] = _xml(tree)
    return main, paths, PreparedScene(_xml(root), applied, warnings, includes)


def missing_message(missing: list[bundle.Reference]) -> str:
    """One message for every file the bundle lacks, each with the places it was looked for."""
    lines = [f"'{r.xml}' references '{r.written}', which is not in the bundle (looked for "
             + ", ".join(f"'{p}'" for p in r.tried) + ")" for r in missing]
    head = (f"{len(missing)} files the scene names are missing from the bundle:\n  "
            if len(missing) > 1 else "")
    return head + "\n  ".join(lines)


def _no_file_as_folder(paths: dict[str, str]) -> None:
    """A bundle is laid out as a directory tree: 'a' cannot be a file and a folder at once."""
    for path in sorted(paths):
        folder = path.rpartition("/")[0]
        while folder:
            if folder in paths:
                raise InvalidArgument(f"bundle lists a file '{folder}' and also '{path}', "
                                      f"which needs '{folder}' to be a folder")
            folder = folder.rpartition("/")[0]


def loadable_path(main: str) -> str:
    """Where the prepared XML sits: beside the main XML, so relative file names resolve."""
    return posixpath.join(posixpath.dirname(main), LOADABLE_NAME)


def prepare(text: bytes, main: str, overrides: dict[str, str]) -> PreparedScene:
    """The loadable copy of a main XML that names no files (the built-in Cornell box)."""
    root, applied, warnings = _prepared_tree(text, main, overrides)
    float_textures(root)
    return PreparedScene(_xml(root), applied, warnings)


def _prepared_tree(text: bytes, main: str, overrides: dict[str, str]
                   ) -> tuple[ET.Element, dict[str, str], list[str]]:
    """The main XML with stable ids and modern integrators, the overrides that apply, and
    warnings.

    ``check_bundle`` follows the file references of this tree with these overrides: nothing
    here may change which file a reference names (a default's new value goes in as an
    override)."""
    try:
        root = bundle.parse_xml(text, main)
    except bundle.BundleError as exc:
        raise InvalidArgument(str(exc)) from None
    if root.tag != "scene":
        raise InvalidArgument(f"'{main}' is not a Mitsuba scene: its root element is "
                              f"<{root.tag}>, expected <scene>")
    declared = bundle.declared_defaults(root)
    warnings = [f"override '{k}={v}' ignored: '{main}' declares no <default name=\"{k}\">"
                for k, v in sorted(overrides.items()) if k not in declared]
    replaced, notes = modernize_integrators(root, main)
    overrides = {**replaced, **{k: LEGACY_INTEGRATORS.get(v, v) for k, v in overrides.items()}}
    assign_ids(root)
    return root, {k: v for k, v in overrides.items() if k in declared}, warnings + notes


def _xml(root: ET.Element) -> bytes:
    return ET.tostring(root, encoding="utf-8", xml_declaration=True)


# Removed in Mitsuba 3.5; their successors optimize the same visibility-dependent parameters.
LEGACY_INTEGRATORS = {"prb_reparam": "prb_projective", "direct_reparam": "direct_projective"}
_LEGACY_PROPERTIES = ("reparam_", )


def modernize_integrators(root: ET.Element, main: str) -> tuple[dict[str, str], list[str]]:
    """Old scenes (the thesis's among them) name integrators Mitsuba 3.9 no longer has and set
    ``reparam_*`` properties its parser rejects; load them with the modern equivalent. A
    default naming one keeps its text and gets the successor as an override, returned."""
    replaced: dict[str, str] = {}
    warnings = []
    for elem in root.iter():
        if elem.tag == "default" and elem.get("value") in LEGACY_INTEGRATORS:
            old = elem.get("value")
            replaced[elem.get("name", "")] = LEGACY_INTEGRATORS[old]
            warnings.append(f"'{main}': default '{elem.get('name')}' names integrator '{old}' "
                            f"(removed in Mitsuba 3.5); using '{LEGACY_INTEGRATORS[old]}'")
        if elem.tag != "integrator":
            continue
        old = elem.get("type", "")
        if old in LEGACY_INTEGRATORS:
            elem.set("type", LEGACY_INTEGRATORS[old])
            warnings.append(f"'{main}': integrator '{old}' was removed in Mitsuba 3.5; using "
                            f"'{LEGACY_INTEGRATORS[old]}'")
        for child in list(elem):
            if child.get("name", "").startswith(_LEGACY_PROPERTIES):
                elem.remove(child)
                warnings.append(f"'{main}': dropped integrator property "
                                f"'{child.get('name')}' (no longer exists)")
    return replaced, warnings


def float_textures(root: ET.Element) -> None:
    """Mitsuba 3.9 loads PNG/JPEG bitmaps as 8-bit data, which cannot carry gradients; asking
    for the variant's float format makes every bitmap texture optimizable as it stands."""
    for elem in root.iter("texture"):
        if elem.get("type") == "bitmap" and not any(
                c.tag == "string" and c.get("name") == "format" for c in elem):
            ET.SubElement(elem, "string", name="format", value="variant")


def assign_ids(root: ET.Element) -> None:
    """Gives every unnamed top-level object the id ``<tag>_<position among its tag>``."""
    taken = {e.get("id") for e in root.iter() if e.get("id")}
    counters: dict[str, int] = {}
    for elem in list(root):
        if elem.tag not in _NAMED_TAGS:
            continue
        n = counters.get(elem.tag, 0)
        counters[elem.tag] = n + 1
        if elem.get("id"):
            continue
        candidate = f"{elem.tag}_{n}"
        while candidate in taken:
            candidate += "_"
        elem.set("id", candidate)
        taken.add(candidate)

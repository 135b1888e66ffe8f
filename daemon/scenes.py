"""Turning an uploaded bundle into a directory Mitsuba can load, without importing Mitsuba.

Three things happen here, all before the engine sees the scene:
- the bundle's files are laid out under the scene's directory, and every file the XML refers
  to must be in the bundle and inside it (``matopt.bundle`` has the path rules);
- objects directly under ``<scene>`` that have no ``id`` get one from their position
  (``shape_3``: the fourth ``<shape>``). Mitsuba would name them after a memory address
  (``object_140092774243456``), so their parameter keys would change on every load and a job
  would lose its parameters after a restart;
- Windows ``\\`` separators in file references become ``/``;
- ``<default>`` overrides are applied only where the XML declares the default; others are
  reported as warnings, never required.
"""

from __future__ import annotations

import os
import shutil
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

from matopt import bundle
from matopt.v1 import matopt_pb2 as pb

from .errors import FailedPrecondition, InvalidArgument
from .store import Store

CORNELL_BOX = Path(__file__).parent / "engine" / "cornell_box.xml"
LOADABLE_NAME = ".matopt-scene.xml"

# Objects whose keys Mitsuba derives from their id when they sit directly under <scene>.
_NAMED_TAGS = ("shape", "bsdf", "emitter", "sensor", "medium", "texture", "volume", "phase")


@dataclass
class PreparedScene:
    directory: Path
    loadable: Path                      # the XML to hand to Mitsuba (ids added)
    overrides: dict[str, str]           # the ones the XML declares
    warnings: list[str] = field(default_factory=list)


def materialize(store: Store, directory: Path, main_file: str,
                files: list[pb.BundleFile], overrides: dict[str, str]) -> str:
    """Lays the bundle out under ``directory``; returns the main XML's bundle path."""
    if not main_file and not files:
        directory.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(CORNELL_BOX, directory / "cornell_box.xml")
        return "cornell_box.xml"
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
    for path, sha in paths.items():
        if not store.has_blob(sha):
            raise FailedPrecondition(f"bundle file '{path}' (sha256 {sha}) has not been uploaded")

    def read(path: str) -> bytes | None:
        return store.blob_file(paths[path]).read_bytes() if path in paths else None

    try:
        for xml, refs in bundle.closure(main, read, overrides).items():
            for ref in refs:
                if ref.path not in paths:
                    raise InvalidArgument(f"'{xml}' references '{ref.written}', which is not in "
                                          f"the bundle (expected at '{ref.path}')")
    except bundle.BundleError as exc:
        raise InvalidArgument(str(exc)) from None

    for path, sha in paths.items():
        dest = directory / path
        dest.parent.mkdir(parents=True, exist_ok=True)
        src = store.blob_file(sha)
        try:
            os.link(src, dest)
        except OSError:
            shutil.copyfile(src, dest)
    return main


def prepare(directory: Path, main: str, overrides: dict[str, str]) -> PreparedScene:
    """Writes the loadable copy of the main XML (stable ids) and sorts out the overrides."""
    source = directory / main
    try:
        root = bundle.parse_xml(source.read_bytes(), main)
    except bundle.BundleError as exc:
        raise InvalidArgument(str(exc)) from None
    if root.tag != "scene":
        raise InvalidArgument(f"'{main}' is not a Mitsuba scene: its root element is "
                              f"<{root.tag}>, expected <scene>")
    declared = bundle.declared_defaults(root)
    warnings = [f"override '{k}={v}' ignored: '{main}' declares no <default name=\"{k}\">"
                for k, v in sorted(overrides.items()) if k not in declared]
    assign_ids(root)
    forward_slashes(root)
    loadable = source.parent / LOADABLE_NAME
    ET.ElementTree(root).write(loadable, encoding="utf-8", xml_declaration=True)
    return PreparedScene(directory, loadable,
                         {k: v for k, v in overrides.items() if k in declared}, warnings)


def forward_slashes(root: ET.Element) -> None:
    """Windows separators in file references, which Mitsuba on Linux would take literally."""
    for elem in root.iter():
        if elem.tag == "string" and elem.get("name") == "filename":
            elem.set("value", elem.get("value", "").replace("\\", "/"))
        elif elem.tag == "include" and elem.get("filename"):
            elem.set("filename", elem.get("filename", "").replace("\\", "/"))


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

"""Writing the optimized state back into the scene: an XML (plus the files it needs) that
Mitsuba loads and renders as the job left it.

A parameter key is a path through the scene graph: ``<id>.<child>...<property>[.value|.data]``
(``blob.interior_medium.albedo.value.value``: the object ``blob``, its interior medium, its
albedo). We follow the same path through the XML: an element by id, then children by their
``name`` attribute or their tag, then the property, whose element is rewritten: ``rgb``/``float``
get the values, bitmap textures and grid volumes point to new files, and meshes whose vertex
data changed are written as PLY (in world space, so their ``to_world`` goes).

An object shared by ``<ref id=...>`` (the Cornell box's BSDFs) holds its values once, in its
definition: the path starts there, and a ``<ref>`` met on the way stands for the definition it
names. A ``<ref>`` takes no properties, so a value written into one would not load.
"""

from __future__ import annotations

import io
import re
import tempfile
import xml.etree.ElementTree as ET
from pathlib import Path

import mitsuba as mi
import numpy as np

from . import images

DIELECTRICS = ("dielectric", "roughdielectric", "thindielectric")
_SUFFIXES = ("value", "data")
# Names plugins give their children in traverse() instead of the children's XML names
# (bumpmap, normalmap, mask: nested_bsdf, nested_texture; twosided: brdf_<n>; blendbsdf: bsdf_<n>).
_NESTED = re.compile(r"nested_(bsdf|texture)|(?:brdf|bsdf)_(\d)")


def _child(elem: ET.Element, part: str, defined: dict[str, ET.Element]) -> ET.Element | None:
    """The child ``part`` names; for a ``<ref>``, the definition it points to (``defined``:
    elements by id), whose tag is what the key's part names."""
    children = [(c.get("name", ""), defined.get(c.get("id", "")) if c.tag == "ref" else c)
                for c in elem]
    children = [(name, c) for name, c in children if c is not None]
    for name, c in children:
        if name == part or (not name and c.tag == part) or f"{name}_{c.tag}" == part:
            return c
    nested = _NESTED.fullmatch(part)
    if nested:
        tag = nested.group(1) or "bsdf"
        of_tag = [c for _, c in children if c.tag == tag]
        index = int(nested.group(2) or 0)
        # twosided with one BSDF uses it for both sides
        return of_tag[min(index, len(of_tag) - 1)] if of_tag else None
    return None


def _numbers(v: np.ndarray) -> str:
    return ", ".join(f"{x:.9g}" for x in np.asarray(v).ravel())


def _safe(key: str) -> str:
    return "".join(c if c.isalnum() or c in "._-" else "_" for c in key)


def _vol(grid: np.ndarray, bbox: tuple[float, ...]) -> bytes:
    z, y, x, c = grid.shape
    header = b"VOL" + bytes([3]) + np.array([1, x, y, z, c], "<i4").tobytes()
    return header + np.array(bbox, "<f4").tobytes() + np.ascontiguousarray(grid, "<f4").tobytes()


def _set_property(owner: ET.Element, prop: str, value: np.ndarray, shape: list[int], key: str,
                  files: dict[str, bytes], directory: Path,
                  defined: dict[str, ET.Element]) -> None:
    elem = _child(owner, prop, defined)
    if elem is None and prop == "eta" and owner.get("type") in DIELECTRICS:
        for c in [c for c in owner if c.get("name") in ("int_ior", "ext_ior", "eta")]:
            owner.remove(c)
        ET.SubElement(owner, "float", name="int_ior", value=_numbers(value))
        ET.SubElement(owner, "float", name="ext_ior", value="1")
        return
    if elem is not None and _set_file(elem, value, shape, key, files, directory):
        return
    for c in [c for c in owner if c is elem or (c.tag == "ref" and defined.get(c.get("id", ""))
                                                is elem)]:
        owner.remove(c)  # a shared value (a <ref>) is replaced here alone
    tag = "rgb" if np.asarray(value).size == 3 else "float"
    ET.SubElement(owner, tag, name=prop, value=_numbers(value))


def _set_file(elem: ET.Element, value: np.ndarray, shape: list[int], key: str,
              files: dict[str, bytes], directory: Path) -> bool:
    """Points a bitmap texture or a grid volume to a new file of ``value``; False for any
    other element."""
    if elem.tag == "texture" and elem.get("type") == "bitmap":
        path = f"textures/{_safe(key)}.exr"
        files[path] = images.encode(np.asarray(value).reshape(shape)[..., :3]
                                    if shape[-1] >= 3 else
                                    np.repeat(np.asarray(value).reshape(shape), 3, axis=2))[0]
    elif elem.tag == "volume" and elem.get("type") == "gridvolume":
        path = f"volumes/{_safe(key)}.vol"
        old = _filename(elem).get("value", "")
        bbox = _vol_bbox(directory / old) if old else (0, 0, 0, 1, 1, 1)
        files[path] = _vol(np.asarray(value).reshape(shape), bbox)
    else:
        return False
    _filename(elem).set("value", path)
    return True


def _filename(elem: ET.Element) -> ET.Element:
    for c in elem:
        if c.tag == "string" and c.get("name") == "filename":
            return c
    return ET.SubElement(elem, "string", name="filename")


def _vol_bbox(path: Path) -> tuple[float, ...]:
    try:
        return tuple(np.frombuffer(path.read_bytes()[24:48], "<f4").tolist())
    except OSError:
        return (0, 0, 0, 1, 1, 1)


def _write_mesh(elem: ET.Element, shape_obj: mi.Shape, key: str, files: dict[str, bytes]) -> None:
    path = f"meshes/{_safe(key.split('.')[0])}.ply"
    with tempfile.TemporaryDirectory() as d:
        out = Path(d) / "mesh.ply"
        shape_obj.write_ply(str(out))
        files[path] = out.read_bytes()
    elem.set("type", "ply")
    for c in [c for c in elem if (c.tag == "transform" and c.get("name") == "to_world")
              or (c.tag == "string" and c.get("name") == "filename")]:
        elem.remove(c)
    ET.SubElement(elem, "string", name="filename", value=path)


def optimized_scene(loadable: Path, overrides: dict[str, str], scene: mi.Scene,
                    values: dict[str, np.ndarray], shapes: dict[str, list[int]]
                    ) -> tuple[dict[str, bytes], list[str]]:
    """(files of the optimized scene, relative to the main XML's folder; keys it could not
    place in the XML). The scene object must hold ``values`` (for meshes written as PLY)."""
    root = ET.parse(loadable).getroot()
    for d in root.iter("default"):  # bake in the overrides the scene was loaded with
        if d.get("name") in overrides:
            d.set("value", overrides[d.get("name")])
    # Definitions only: a later <ref> to the same id must not stand in for its definition.
    by_id = {e.get("id"): e for e in root.iter() if e.get("id") and e.tag != "ref"}
    shapes_by_id = {s.id(): s for s in scene.shapes()}
    files: dict[str, bytes] = {}
    unplaced = []
    for key, value in values.items():
        parts = key.split(".")
        while parts and parts[-1] in _SUFFIXES:
            parts.pop()
        elem = by_id.get(parts[0])
        if elem is None:
            unplaced.append(key)
            continue
        if parts[-1].startswith("vertex_") and elem.tag == "shape":
            if parts[0] in shapes_by_id:
                _write_mesh(elem, shapes_by_id[parts[0]], key, files)
            else:
                unplaced.append(key)
            continue
        if len(parts) == 1:  # the key names the object itself (a grid volume's data)
            if not _set_file(elem, value, shapes.get(key, []), key, files, loadable.parent):
                unplaced.append(key)
            continue
        for part in parts[1:-1]:
            elem = _child(elem, part, by_id) if elem is not None else None
        if elem is None:
            unplaced.append(key)
            continue
        _set_property(elem, parts[-1], value, shapes.get(key, []), key, files, loadable.parent,
                      by_id)
    buf = io.BytesIO()
    ET.ElementTree(root).write(buf, encoding="utf-8", xml_declaration=True)
    files["scene_optimized.xml"] = buf.getvalue()
    return files, unplaced

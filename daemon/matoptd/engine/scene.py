"""Loading a prepared scene and describing what a client needs to know about it."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import mitsuba as mi

from ..engine_api import InvalidInput
from . import parameters


@dataclass
class Description:
    sensors: list[tuple[str, int, int]]  # (id, width, height)
    has_media: bool
    parameters: list[parameters.Info]


# Mitsuba's own files: its plugins (plugins/<type>.so) and data (data/ior/*.spd for named
# conductors), which it finds through the same file resolver as a scene's files.
MITSUBA_DIR = Path(mi.__file__).parent


def preload_plugins() -> None:
    """Loads every plugin Mitsuba ships, once per process. A plugin not loaded yet is looked
    up as ``plugins/<type>.so`` through the file resolver, whose first folder is the scene's:
    loaded beforehand, no scene file can stand in for one."""
    manager = mi.PluginManager.instance()
    for plugin in sorted((MITSUBA_DIR / "plugins").glob("*.so")):
        manager.plugin_type(plugin.stem)


def confine(folder: Path, root: Path) -> None:
    """Resets Mitsuba's global file resolver to the scene's folder, the bundle's root and
    Mitsuba's own: the current directory, which Mitsuba adds at start-up, and any folder a
    previous load added are gone, so a relative file name finds nothing outside the scene. The
    root stands for the directory the scene's author ran Mitsuba from (``matopt_api.bundle``
    follows the same order and refuses a name that would lead outside before it is found)."""
    resolver = mi.file_resolver()
    resolver.clear()
    resolver.append(str(folder))
    resolver.append(str(root))
    resolver.append(str(MITSUBA_DIR))


def load(loadable: Path, overrides: dict[str, str], display: str,
         keys: list[str] | None = None, *, root: Path) -> mi.Scene:
    """Loads the XML; Mitsuba's own message (with the file and the offending tag) on failure,
    with the scene's files named by their bundle paths (relative to ``root``, the bundle's
    folder), never by where this process keeps them.

    Mitsuba's parser can merge the meshes that share a BSDF into one anonymous mesh, which
    renders the same, faster (fewer shapes to trace and to dispatch over: 4% an iteration on
    the Cornell box), but the merged shapes lose their ids and with them their parameter
    keys. Without ``keys`` (listing every parameter) nothing is merged; with the keys a job
    optimizes, meshes are merged unless that would lose one of them.
    """
    confine(loadable.parent, root)
    try:
        if keys is not None:
            merged = mi.load_file(str(loadable), optimize=True, **overrides)
            if all(k in mi.traverse(merged) for k in keys):
                return merged
            del merged
        return mi.load_file(str(loadable), optimize=False, **overrides)
    except Exception as exc:  # Mitsuba raises RuntimeError/ValueError with the parser's text
        message = scrub(str(exc), loadable, display, root)
        raise InvalidInput(f"Mitsuba cannot load '{display}': {message}") from None


def scrub(message: str, loadable: Path, display: str, root: Path) -> str:
    """Mitsuba's message with the prepared XML named as the user's main file, bundle files by
    their bundle paths, and no other path of this machine but Mitsuba's own."""
    message = message.replace(str(loadable), display)
    message = message.replace(f"{root}{os.sep}", "").replace(str(root), ".")
    return message.replace(str(root.parent.parent), "<worker cache>").strip()


def has_media(scene: mi.Scene) -> bool:
    """Whether any shape bounds a medium or any sensor sits in one (then prbvolpath is needed)."""
    for shape in scene.shapes():
        if shape.interior_medium() is not None or shape.exterior_medium() is not None:
            return True
    return any(s.get_medium() is not None for s in scene.sensors())


def describe(scene: mi.Scene) -> Description:
    sensors = []
    for i, sensor in enumerate(scene.sensors()):
        size = sensor.film().crop_size()
        sensors.append((sensor.id() or f"sensor_{i}", int(size[0]), int(size[1])))
    return Description(sensors, has_media(scene), parameters.describe(mi.traverse(scene)))

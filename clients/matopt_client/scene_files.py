"""Finding a scene's files on disk as Mitsuba would, and laying them out as a bundle.

Mitsuba looks a file name up from the folder of the XML that names it, then from the
directory it was started in. Scenes are often written to be run from a project's root, with
names such as ``scenes\\shared\\meshes\\bunny.ply`` for files shared between scenes. The bundle
therefore has a root: the folder its paths are relative to, which stands for that starting
directory on the daemon (``matopt_api.bundle`` has the lookup rules both sides follow). Given
no root, the first of these under which every file is found is used: the main XML's folder,
the current directory (when it holds the XML), then the XML's parent folders, nearest first.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from matopt_api import bundle


class SceneFilesError(ValueError):
    """A scene whose files cannot all be found or used; the message says which and why."""


@dataclass
class _Attempt:
    """The bundle read with one candidate root."""

    root: Path
    main_file: str
    files: dict[str, Path]
    missing: list[bundle.Reference]


def find_bundle(main_xml: str | os.PathLike, overrides: dict[str, str] | None = None,
                root: str | os.PathLike | None = None) -> tuple[str, dict[str, Path]]:
    """The main XML's bundle path and every file the bundle needs (bundle path -> disk path).

    ``root`` is the folder the scene's file names are relative to (the directory its author
    ran Mitsuba from); without it, candidates are tried as the module says. Raises
    ``SceneFilesError`` listing every missing file, each with where it was looked for.
    """
    main = Path(os.path.abspath(main_xml))
    if not main.is_file():
        raise SceneFilesError(f"scene file '{main_xml}' does not exist")
    if root is not None:
        given = Path(os.path.abspath(root))
        if not given.is_dir():
            raise SceneFilesError(f"--root '{root}' is not a directory")
        if not main.is_relative_to(given):
            main, given = main.resolve(), given.resolve()
        if not main.is_relative_to(given):
            raise SceneFilesError(f"scene file '{main_xml}' is not inside --root '{root}': "
                                  "the root is the folder the whole scene sits in")
        roots = [given]
    else:
        roots = candidate_roots(main)
    attempts: list[_Attempt] = []
    errors: list[bundle.BundleError] = []
    for candidate in roots:
        try:
            attempt = _read(main, candidate, overrides)
        except bundle.BundleError as exc:  # e.g. a '..' leading outside this root
            errors.append(exc)
            continue
        if not attempt.missing:
            return attempt.main_file, attempt.files
        attempts.append(attempt)
    if not attempts:
        raise SceneFilesError(str(errors[0]))
    raise SceneFilesError(missing_message(attempts, explicit_root=root is not None))


def candidate_roots(main: Path) -> list[Path]:
    """The main XML's folder, the current directory if it holds the XML, then the XML's other
    parent folders nearest first (not the filesystem's root, not above the home folder)."""
    folder = main.parent
    cwd = Path(os.path.abspath(os.getcwd()))
    parents = [p for p in folder.parents if p != p.parent]
    home = Path.home()
    if folder.is_relative_to(home):
        parents = [p for p in parents if p.is_relative_to(home)]
    found = [folder] + ([cwd] if main.is_relative_to(cwd) else []) + parents
    return list(dict.fromkeys(found))


def _read(main: Path, root: Path, overrides: dict[str, str] | None) -> _Attempt:
    main_file = bundle.normalize(main.relative_to(root).as_posix())

    def read(path: str) -> bytes | None:
        return (root / path).read_bytes() if (root / path).is_file() else None

    found = bundle.closure(main_file, read, overrides=overrides,
                           exists=lambda path: (root / path).is_file())
    files, missing = {main_file: main}, []
    for refs in found.values():
        for ref in refs:
            if (root / ref.path).is_file():
                files[ref.path] = root / ref.path
            else:
                missing.append(ref)
    return _Attempt(root, main_file, files, missing)


def missing_message(attempts: list[_Attempt], explicit_root: bool) -> str:
    """Every missing file once, with every place looked at under every root tried."""
    looked: dict[tuple[Path, str], list[Path]] = {}
    for attempt in attempts:
        for ref in attempt.missing:
            places = looked.setdefault((attempt.root / ref.xml, ref.written), [])
            places += [attempt.root / p for p in ref.tried if attempt.root / p not in places]
    lines = [f"'{written}', named in {xml}; looked for "
             + ", ".join(str(p) for p in places) for (xml, written), places in looked.items()]
    roots = ", ".join(str(a.root) for a in attempts)
    advice = ("put each file at one of the places listed, or correct its name in the XML"
              if explicit_root else
              "put each file at one of the places listed, correct its name in the XML, or give "
              "--root DIR, the folder the scene's file names are relative to (the directory "
              "Mitsuba was run from)")
    count = f"{len(lines)} files" if len(lines) > 1 else "a file"
    return (f"{count} the scene names cannot be found (each name is looked up from the folder "
            f"of the XML naming it, then from the root, tried as: {roots}):\n  "
            + "\n  ".join(lines) + f"\n{advice[0].upper()}{advice[1:]}.")

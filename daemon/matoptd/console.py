"""The ``matoptd`` command, which first checks that this install has what the daemon needs.

A client-only install (``pip install matopt-mitsuba``) holds the ``matoptd`` package too, but
not the ``daemon`` extra (Mitsuba, Dr.Jit, gRPC's health and reflection services). The list
is read from the installed distribution's metadata, where pyproject.toml declares it, and
nothing of the daemon is imported before it is complete: a missing piece is one line naming
the extra, not a traceback from deep inside the server.
"""

from __future__ import annotations

import re
import sys
from importlib import metadata

DISTRIBUTION = "matopt-mitsuba"
EXTRA = "daemon"
USAGE_ERROR = 2  # as for a wrong command line: the command cannot run as installed


def missing_requirements(extra: str = EXTRA) -> list[str]:
    """The distributions ``extra`` requires that are not installed; none when this runs from
    a source tree without installed metadata (nothing to check against)."""
    try:
        requires = metadata.requires(DISTRIBUTION) or []
    except metadata.PackageNotFoundError:
        return []
    missing = []
    for requirement in requires:
        spec, _, marker = requirement.partition(";")
        if not re.search(rf"extra\s*==\s*[\"']{re.escape(extra)}[\"']", marker):
            continue
        name = re.match(r"[A-Za-z0-9._-]+", spec.strip()).group()
        try:
            metadata.distribution(name)
        except metadata.PackageNotFoundError:
            missing.append(name)
    return missing


def main() -> None:
    missing = missing_requirements()
    if missing:
        print(f"matoptd: error: this install has the clients only (missing "
              f"{', '.join(missing)}); install the daemon with: "
              f"pip install \"{DISTRIBUTION}[{EXTRA}]\"", file=sys.stderr)
        sys.exit(USAGE_ERROR)
    from matoptd.main import main as serve

    serve()

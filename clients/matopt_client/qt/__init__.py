"""matopt-qt: the desktop client of matoptd (PySide6), the thesis tool's workflow over gRPC.

Like the rest of the ``matopt`` package it imports neither mitsuba nor drjit: the daemon
renders, this only talks to it. Install with ``pip install "matopt-mitsuba[qt]"``.
"""

from __future__ import annotations

import sys
from typing import Sequence


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``matopt-qt``; a missing PySide6 is one line with the fix, not a trace."""
    try:
        from matopt_client.qt.app import main as run
    except ImportError as exc:
        if (exc.name or "").split(".")[0] not in ("PySide6", "shiboken6"):
            raise
        print(f"matopt-qt: error: PySide6 is not installed ({exc}); "
              f"install it with: pip install \"matopt-mitsuba[qt]\"", file=sys.stderr)
        return 1
    return run(argv)

"""CPU core lists as people read them: what a worker's device line and the daemon's start-up
log print. A leaf module, so that the engine (which describes its own device) and the
workers (which place processes on cores) share it without importing each other."""

from __future__ import annotations


def core_ranges(cores) -> str:
    """(0, 1, 2, 5) -> '0-2,5'."""
    parts, start = [], None
    for i, c in enumerate(cores):
        if start is None:
            start = c
        if i + 1 == len(cores) or cores[i + 1] != c + 1:
            parts.append(f"{start}-{c}" if c != start else f"{c}")
            start = None
    return ",".join(parts)

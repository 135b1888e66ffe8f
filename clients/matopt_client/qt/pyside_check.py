"""A check for PySide6 builds that corrupt the reference count of ``None``.

PySide6-Essentials 6.12.0 wheels, on CPython before 3.12 (where ``None`` is not yet
immortal), return ``None`` from every void method without taking a reference: each call to
``QPainter.drawLine``, ``QWidget.update`` and the like drops None's count by one, and after a
few thousand (one second of a live plot) the interpreter aborts with "Fatal Python error:
none_dealloc". The app refuses to start on such a build, naming the fix, instead of crashing
mid-job; the tests skip instead of taking the whole pytest process down.
"""

from __future__ import annotations

import sys


def none_refcount_bug() -> bool:
    """True if void PySide6 calls drop a reference to None (measured, not guessed by version)."""
    if sys.version_info >= (3, 12):
        return False  # None is immortal: such a bug is harmless
    from PySide6.QtCore import QPointF
    from PySide6.QtGui import QPainterPath

    path = QPainterPath(QPointF(0.0, 0.0))
    before = sys.getrefcount(None)
    for i in range(20):
        path.lineTo(QPointF(float(i), 1.0))
    lost = before - sys.getrefcount(None)
    # Put back what was taken, so that the check itself cannot be what crashes later.
    for _ in range(max(lost, 0)):
        _leak_none()
    return lost >= 10


_kept: list = []


def _leak_none() -> None:
    _kept.append(None)


def problem() -> str | None:
    """The message to show when this PySide6 cannot be used, else None."""
    if not none_refcount_bug():
        return None
    import PySide6

    return (f"PySide6 {PySide6.__version__} corrupts Python {sys.version_info.major}."
            f"{sys.version_info.minor}'s reference count of None and would crash within "
            f"seconds; install another version: pip install \"PySide6-Essentials>=6.6,!=6.12.0\"")

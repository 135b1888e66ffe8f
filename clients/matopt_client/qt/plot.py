"""The loss, and each parameter's relative error when the job has ground truth, against
optimizing time, drawn with QPainter (what ``matopt job report`` plots, live).

The thesis compared runs by error over *run time*, not over iterations (a dual-buffer step
costs two renders), so the x axis is ``IterationRecord.seconds``. Losses fall over orders of
magnitude, so the y axis is logarithmic whenever every loss is positive (``dual_buffer`` can
give negative estimates; then it is linear). A few hundred points are drawn on every update,
which QPainter does in well under a millisecond: no plotting library is needed.
"""

from __future__ import annotations

import math
from typing import Iterable

from PySide6.QtCore import QPointF, QRectF, QSize, Qt
from PySide6.QtGui import QColor, QFont, QPainter, QPainterPath, QPaintEvent, QPen
from PySide6.QtWidgets import QSizePolicy, QWidget

LINE = QColor(31, 119, 180)
# Parameter-error curves (matplotlib's tab10, without the loss's blue and the best's red).
ERRORS = [QColor(255, 127, 14), QColor(44, 160, 44), QColor(148, 103, 189),
          QColor(140, 86, 75), QColor(227, 119, 194), QColor(188, 189, 34), QColor(23, 190, 207)]
BEST = QColor(214, 39, 40)
TARGET = QColor(120, 120, 120)
GRID = QColor(228, 228, 228)


def nice_ticks(low: float, high: float, count: int = 5) -> list[float]:
    """Round tick positions (1, 2, 5 times a power of ten) covering [low, high]."""
    if not (math.isfinite(low) and math.isfinite(high)) or high <= low:
        return [low]
    raw = (high - low) / max(count, 1)
    magnitude = 10 ** math.floor(math.log10(raw))
    step = next(m * magnitude for m in (1, 2, 5, 10) if m * magnitude >= raw)
    first = math.ceil(low / step) * step
    ticks, value = [], first
    while value <= high + step * 1e-9:
        ticks.append(0.0 if abs(value) < step * 1e-9 else value)
        value += step
    return ticks


def log_ticks(low: float, high: float, most: int = 6) -> list[float]:
    """Ticks for a log axis spanning 10**low .. 10**high: the powers of ten inside, or, on a
    range under a decade or two, 1-2-5 (then 1-2-3-5) steps, so that a flat curve still gets
    labels; never more than ``most``."""
    decades = range(math.floor(low), math.ceil(high) + 1)
    ticks: list[float] = []
    for mantissas in ((1,), (1, 2, 5), (1, 2, 3, 5), (1, 1.5, 2, 3, 4, 5, 6, 7, 8, 9)):
        ticks = [m * 10.0 ** e for e in decades for m in mantissas
                 if low <= math.log10(m * 10.0 ** e) <= high]
        if len(ticks) >= 2:
            break
    step = max(1, math.ceil(len(ticks) / most))
    return ticks[::step] or [10 ** low]


def tick_label(value: float) -> str:
    """Short axis labels: 0.02, 1.5, 2e-4, 1.5e4."""
    if value == 0:
        return "0"
    if abs(value) >= 1e4 or abs(value) < 1e-3:
        mantissa, exponent = f"{value:.1e}".split("e")
        return f"{mantissa.rstrip('0').rstrip('.')}e{int(exponent)}"
    return f"{value:.3g}"


def short_key(key: str) -> str:
    """'shape_2.bsdf.base_color.value' -> 'base_color'."""
    parts = [p for p in key.split(".") if p not in ("value", "data")]
    return parts[-1] if parts else key


class LossPlot(QWidget):
    """Loss (y) against seconds (x), the best point marked, the min-error target dashed; with
    ground truth, each parameter's relative error as a thinner curve on the same log axis."""

    def __init__(self, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.points: dict[int, tuple[float, float]] = {}  # iteration -> (seconds, loss)
        # parameter key -> iteration -> (seconds, relative error against the ground truth)
        self.errors: dict[str, dict[int, tuple[float, float]]] = {}
        self.target: float | None = None
        # The daemon's best iteration when known: for dual_buffer it is the best mean over a
        # window of iterations, not the lowest single (noisy, possibly negative) estimate.
        self.best_iteration: int | None = None
        self.title = "loss (and parameter error) vs. optimizing time"
        self.setSizePolicy(QSizePolicy.Policy.Expanding, QSizePolicy.Policy.Expanding)
        self.setMinimumSize(260, 160)

    def sizeHint(self) -> QSize:
        return QSize(420, 220)

    # -- data ----------------------------------------------------------------------------------

    def clear(self) -> None:
        self.points.clear()
        self.errors.clear()
        self.best_iteration = None
        self.update()

    def set_best_iteration(self, iteration: int | None) -> None:
        self.best_iteration = iteration if iteration is not None and iteration >= 0 else None
        self.update()

    def add(self, iteration: int, seconds: float, loss: float,
            errors: dict[str, float] | None = None) -> None:
        """Adds (or replaces) one iteration's point; the history and the live stream may
        both deliver the same iteration, which then counts once."""
        self._put(iteration, seconds, loss, errors)
        self.update()

    def extend(self, records: Iterable[tuple[int, float, float, dict[str, float]]]) -> None:
        for record in records:
            self._put(*record)
        self.update()

    def _put(self, iteration: int, seconds: float, loss: float,
             errors: dict[str, float] | None = None) -> None:
        self.points[iteration] = (seconds, loss)
        for key, value in (errors or {}).items():
            self.errors.setdefault(key, {})[iteration] = (seconds, value)

    def error_points(self) -> dict[str, list[tuple[float, float]]]:
        """Per parameter, (seconds, relative error) in iteration order, positive and finite
        (a log axis cannot show an exact 0)."""
        return {key: [series[i] for i in sorted(series)
                      if math.isfinite(series[i][0]) and math.isfinite(series[i][1])
                      and series[i][1] > 0]
                for key, series in self.errors.items()}

    def set_target(self, value: float | None) -> None:
        self.target = value if value and value > 0 else None
        self.update()

    def finite_points(self) -> list[tuple[float, float]]:
        """(seconds, loss) in iteration order, without skipped (NaN/Inf) steps."""
        return [self.points[i] for i in sorted(self.points)
                if math.isfinite(self.points[i][1]) and math.isfinite(self.points[i][0])]

    def best(self) -> tuple[float, float] | None:
        """The daemon's best iteration if known and plotted, else the lowest loss."""
        if self.best_iteration in self.points:
            point = self.points[self.best_iteration]
            if math.isfinite(point[0]) and math.isfinite(point[1]):
                return point
        pts = self.finite_points()
        return min(pts, key=lambda p: p[1]) if pts else None

    # -- drawing -------------------------------------------------------------------------------

    def paintEvent(self, event: QPaintEvent) -> None:  # noqa: N802 - Qt's name
        painter = QPainter(self)
        painter.setRenderHint(QPainter.RenderHint.Antialiasing)
        painter.fillRect(self.rect(), Qt.GlobalColor.white)
        font = QFont(painter.font())
        font.setPointSizeF(max(7.0, font.pointSizeF() - 1))
        painter.setFont(font)
        metrics = painter.fontMetrics()
        left, right = metrics.horizontalAdvance("0.0001") + 12, 12
        top, bottom = metrics.height() + 8, metrics.height() * 2 + 10
        area = QRectF(left, top, max(10, self.width() - left - right),
                      max(10, self.height() - top - bottom))  # until the labels are known
        painter.setPen(Qt.GlobalColor.black)
        painter.drawText(QRectF(0, 2, self.width(), metrics.height()),
                         Qt.AlignmentFlag.AlignHCenter, self.title)

        pts = self.finite_points()
        if not pts:
            painter.setPen(TARGET)
            painter.drawRect(area)
            painter.drawText(area, Qt.AlignmentFlag.AlignCenter, "no iterations yet")
            return

        xs, ys = [p[0] for p in pts], [p[1] for p in pts]
        curves = {k: c for k, c in self.error_points().items() if c}
        ys_range = ys + ([self.target] if self.target is not None else [])
        log_y = all(y > 0 for y in ys_range)
        if log_y:  # errors share the loss's axis only when it is logarithmic
            ys_range += [y for c in curves.values() for _, y in c]
        else:
            curves = {}
        x0, x1 = 0.0, max(max(xs), 1e-3)
        if log_y:
            y0, y1 = math.log10(min(ys_range)), math.log10(max(ys_range))
            if y1 - y0 < 0.3:  # a flat curve: show at least a factor of two
                middle = (y0 + y1) / 2
                y0, y1 = middle - 0.15, middle + 0.15
            pad = (y1 - y0) * 0.05
            y0, y1 = y0 - pad, y1 + pad
            y_ticks = log_ticks(y0, y1)
        else:
            y0, y1 = min(0.0, min(ys_range)), max(ys_range)
            pad = (y1 - y0) * 0.05 or abs(y1) * 0.1 or 1.0
            y0, y1 = y0 - (pad if y0 < 0 else 0), y1 + pad
            y_ticks = nice_ticks(y0, y1, 4)
        labels = [tick_label(y) for y in y_ticks]
        left = max(metrics.horizontalAdvance(t) for t in labels + ["0.01"]) + 10
        area = QRectF(left, top, max(10, self.width() - left - right),
                      max(10, self.height() - top - bottom))

        def to_screen(x: float, y: float) -> QPointF:
            fy = math.log10(y) if log_y else y
            sx = area.left() + (x - x0) / (x1 - x0) * area.width()
            sy = area.bottom() - (fy - y0) / (y1 - y0) * area.height()
            return QPointF(sx, sy)

        # Grid and tick labels.
        x_ticks = nice_ticks(x0, x1, 5)
        for y, label in zip(y_ticks, labels):
            p = to_screen(x0, y)
            painter.setPen(QPen(GRID, 1))
            painter.drawLine(QPointF(area.left(), p.y()), QPointF(area.right(), p.y()))
            painter.setPen(Qt.GlobalColor.darkGray)
            painter.drawText(QRectF(0, p.y() - metrics.height() / 2, left - 4, metrics.height()),
                             Qt.AlignmentFlag.AlignRight | Qt.AlignmentFlag.AlignVCenter,
                             label)
        for x in x_ticks:
            p = to_screen(x, 10 ** y0 if log_y else y0)
            painter.setPen(QPen(GRID, 1))
            painter.drawLine(QPointF(p.x(), area.top()), QPointF(p.x(), area.bottom()))
            painter.setPen(Qt.GlobalColor.darkGray)
            painter.drawText(QRectF(p.x() - 30, area.bottom() + 2, 60, metrics.height()),
                             Qt.AlignmentFlag.AlignHCenter, tick_label(x))
        painter.drawText(QRectF(area.left(), area.bottom() + metrics.height() + 2, area.width(),
                                metrics.height()),
                         Qt.AlignmentFlag.AlignHCenter,
                         "seconds" + ("   (y on a log scale)" if log_y else ""))
        painter.setPen(QPen(Qt.GlobalColor.gray, 1))
        painter.drawRect(area)

        painter.save()
        painter.setClipRect(area.adjusted(-1, -1, 1, 1))
        if self.target is not None and (not log_y or self.target > 0):
            p = to_screen(x0, self.target)
            painter.setPen(QPen(TARGET, 1, Qt.PenStyle.DashLine))
            painter.drawLine(QPointF(area.left(), p.y()), QPointF(area.right(), p.y()))
        path = QPainterPath(to_screen(*pts[0]))
        for x, y in pts[1:]:
            path.lineTo(to_screen(x, y))
        for n, (key, curve) in enumerate(curves.items()):
            error_path = QPainterPath(to_screen(*curve[0]))
            for x, y in curve[1:]:
                error_path.lineTo(to_screen(x, y))
            painter.setPen(QPen(ERRORS[n % len(ERRORS)], 1.0))
            painter.drawPath(error_path)
        painter.setPen(QPen(LINE, 1.5))
        painter.drawPath(path)
        best = self.best() or pts[0]
        painter.setPen(Qt.PenStyle.NoPen)
        painter.setBrush(BEST)
        painter.drawEllipse(to_screen(*best), 3.5, 3.5)
        painter.restore()
        painter.setPen(BEST)
        painter.drawText(QRectF(area.left() + 4, area.top() + 2, area.width() - 8,
                                metrics.height()),
                         Qt.AlignmentFlag.AlignRight,
                         f"best {best[1]:.3g} at {best[0]:.1f} s")
        if curves:  # a legend: the loss, then each parameter's relative error
            y = area.top() + 2
            for n, (label, colour) in enumerate(
                    [("loss", LINE)] + [(f"{short_key(k)} rel. error", ERRORS[i % len(ERRORS)])
                                        for i, k in enumerate(curves)]):
                painter.setPen(colour)
                painter.drawText(QRectF(area.left() + 4, y + n * metrics.height(),
                                        area.width() / 2, metrics.height()),
                                 Qt.AlignmentFlag.AlignLeft, label)

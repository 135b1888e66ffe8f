"""The scene's parameters as a table: what to optimize, and how.

One row per parameter of ``ListSceneParameters``: a checkbox (optimize it), the key, its
kind, its value, learning rate, min and max, and the value of the iteration (or result) being
shown. Scalar and RGB values can be edited; an edited value becomes the job's
``ParameterSpec.initial_value`` (the thesis workflow: grey the walls, then recover them).

Only what the user changed from the scene's defaults goes into the spec: the daemon fills in
everything else, so the spec stays what the user meant even if the daemon's defaults change.
Whether a value is legal is the daemon's to say (its message names the key); the table only
checks that a cell parses, so the two can never disagree.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Iterable, Sequence

from PySide6.QtCore import Qt, Signal
from PySide6.QtGui import QBrush, QColor, QIcon, QPixmap
from PySide6.QtWidgets import (QAbstractItemView, QHBoxLayout, QHeaderView, QLabel, QLineEdit,
                               QTableWidget, QTableWidgetItem, QVBoxLayout, QWidget)

from matopt_client import client as mc, workflow
from matopt_api import costs, enums
from matopt_api.v1 import matopt_pb2 as pb

# "Current" sits next to "Value" so that start and current values read side by side.
COLUMNS = ["Opt.", "Key", "Kind", "Value", "Current", "Learning rate", "Min", "Max"]
OPT, KEY, KIND, VALUE, CURRENT, LR, MIN, MAX = range(len(COLUMNS))
EDITABLE_KINDS = (pb.PARAMETER_KIND_SCALAR, pb.PARAMETER_KIND_RGB)
INVALID = QColor(255, 205, 205)


def format_float(value: float) -> str:
    """float32 values printed as short as they read back (0.57, not 0.5699999928)."""
    if math.isinf(value):
        return "inf" if value > 0 else "-inf"
    return f"{mc.short_float(value):g}"


def format_values(values: Sequence[float]) -> str:
    return ", ".join(format_float(v) for v in values)


def parse_values(text: str) -> list[float]:
    """``"0.5"`` or ``"0.5, 0.2 0.1"`` (commas or spaces); ValueError names the bad part."""
    parts = [p for p in text.replace(",", " ").split() if p]
    out = []
    for part in parts:
        try:
            out.append(float(part))
        except ValueError:
            raise ValueError(f"'{part}' is not a number") from None
    return out


def swatch(values: Sequence[float]) -> QIcon:
    """A small square in the colour an RGB reflectance shows on screen (linear -> sRGB)."""
    def srgb(c: float) -> int:
        c = min(max(c, 0.0), 1.0)
        c = 12.92 * c if c <= 0.0031308 else 1.055 * c ** (1 / 2.4) - 0.055
        return round(c * 255)
    pixmap = QPixmap(14, 14)
    pixmap.fill(QColor(*(srgb(v) for v in values[:3])))
    return QIcon(pixmap)


@dataclass
class Row:
    """One parameter and what the user set for it. ``initial`` is the start value when it
    differs from the scene's (edited, or taken over from an earlier job's spec)."""

    parameter: pb.Parameter
    initial: list[float] | None = None
    initial_blob: str | None = None  # a large start value (.npy) an earlier job's spec named

    @property
    def editable(self) -> bool:
        return self.parameter.kind in EDITABLE_KINDS and len(self.parameter.value) > 0


class ParamsTable(QWidget):
    """The table with a filter line above it; ``changed`` fires on every edit."""

    changed = Signal()

    def __init__(self, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        layout = QVBoxLayout(self)
        layout.setContentsMargins(0, 0, 0, 0)
        top = QHBoxLayout()
        self.filter = QLineEdit()
        self.filter.setPlaceholderText("Filter keys…")
        self.filter.setClearButtonEnabled(True)
        self.filter.textChanged.connect(self._apply_filter)
        self.summary = QLabel("")
        top.addWidget(self.filter, 1)
        top.addWidget(self.summary)
        layout.addLayout(top)
        self.table = QTableWidget(0, len(COLUMNS))
        self.table.setHorizontalHeaderLabels(COLUMNS)
        self.table.horizontalHeaderItem(OPT).setToolTip("optimize this parameter")
        self.table.horizontalHeaderItem(VALUE).setToolTip(
            "the value the job starts from (scalars and RGB colours can be edited)")
        self.table.horizontalHeaderItem(CURRENT).setToolTip(
            "the value of the iteration being shown, or of the best/last result")
        self.table.setWordWrap(False)
        self.table.verticalHeader().setVisible(False)
        self.table.setSelectionBehavior(QAbstractItemView.SelectionBehavior.SelectRows)
        self.table.setEditTriggers(QAbstractItemView.EditTrigger.DoubleClicked
                                   | QAbstractItemView.EditTrigger.EditKeyPressed
                                   | QAbstractItemView.EditTrigger.AnyKeyPressed)
        header = self.table.horizontalHeader()
        header.setSectionResizeMode(QHeaderView.ResizeMode.Interactive)
        header.setStretchLastSection(True)
        self.table.itemChanged.connect(self._item_changed)
        layout.addWidget(self.table)
        self.rows: list[Row] = []
        self._filling = False

    # -- content -------------------------------------------------------------------------------

    def set_parameters(self, parameters: Iterable[pb.Parameter]) -> None:
        """Shows a scene's parameters, none selected, values and settings at their defaults."""
        self.rows = [Row(p) for p in parameters]
        self._filling = True
        try:
            self.table.setRowCount(len(self.rows))
            for i, row in enumerate(self.rows):
                self._fill(i, row)
        finally:
            self._filling = False
        self.table.resizeColumnsToContents()
        for column, low, high in ((KEY, 140, 280), (KIND, 60, 130), (VALUE, 90, 150),
                                  (CURRENT, 110, 150), (LR, 50, 90), (MIN, 40, 70),
                                  (MAX, 40, 70)):
            self.table.setColumnWidth(column, min(max(self.table.columnWidth(column), low),
                                                  high))
        self._apply_filter(self.filter.text())
        self._update_summary()
        self.changed.emit()

    def _fill(self, i: int, row: Row) -> None:
        p = row.parameter
        opt = QTableWidgetItem()
        opt.setFlags(Qt.ItemFlag.ItemIsUserCheckable | Qt.ItemFlag.ItemIsEnabled
                     | Qt.ItemFlag.ItemIsSelectable)
        opt.setCheckState(Qt.CheckState.Unchecked)
        self.table.setItem(i, OPT, opt)
        self.table.setItem(i, KEY, _readonly(p.key, tooltip=_key_tooltip(p)))
        kind = enums.short_name(pb.ParameterKind, p.kind).replace("_", " ").lower()
        shape = "×".join(map(str, p.shape))
        self.table.setItem(i, KIND, _readonly(f"{kind} {shape}" if shape and kind != "rgb"
                                              else kind))
        if row.editable:
            value = QTableWidgetItem(format_values(p.value))
            value.setToolTip("double-click to set the value the job starts from")
        else:
            n = math.prod(p.shape) if p.shape else len(p.value)
            text, tip = format_values(p.value) if p.value else f"{n:,} values", ""
            if costs.is_large(p.shape):  # say what selecting it costs
                size = costs.format_size(n * costs.DEVICE_BYTES_PER_VALUE)
                text, tip = f"{text} (large: {size} to optimize)", costs.parameter_cost(
                    p.key, p.shape) + "\n"
            value = _readonly(text, tooltip=tip + "only scalars and RGB colours can be "
                                                  "edited here")
        if p.kind == pb.PARAMETER_KIND_RGB and len(p.value) >= 3:
            value.setIcon(swatch(p.value))
        self.table.setItem(i, VALUE, value)
        for column, number in ((LR, p.default_learning_rate), (MIN, p.min), (MAX, p.max)):
            item = QTableWidgetItem(format_float(number))
            item.setToolTip("the scene's default; edit to override for this job")
            self.table.setItem(i, column, item)
        self.table.setItem(i, CURRENT, _readonly(""))

    def clear(self) -> None:
        self.rows = []
        self.table.setRowCount(0)
        self._update_summary()

    def row_of(self, key: str) -> int:
        for i, row in enumerate(self.rows):
            if row.parameter.key == key:
                return i
        raise KeyError(key)

    def keys(self) -> list[str]:
        return [r.parameter.key for r in self.rows]

    # -- what the user sets --------------------------------------------------------------------

    def set_checked(self, key: str, checked: bool = True) -> None:
        state = Qt.CheckState.Checked if checked else Qt.CheckState.Unchecked
        self.table.item(self.row_of(key), OPT).setCheckState(state)

    def checked_keys(self) -> list[str]:
        return [row.parameter.key for i, row in enumerate(self.rows)
                if self.table.item(i, OPT).checkState() == Qt.CheckState.Checked]

    def set_cell(self, key: str, column: int, text: str) -> None:
        """What typing into a cell does (tests, and "use result as start values")."""
        self.table.item(self.row_of(key), column).setText(text)

    def set_initial(self, key: str, values: Sequence[float]) -> None:
        i = self.row_of(key)
        if self.rows[i].editable:
            self.set_cell(key, VALUE, format_values(values))
        else:
            self.rows[i].initial = list(values)
            self.table.item(i, VALUE).setText(f"{len(values)} values (set)")

    def errors(self) -> list[str]:
        """A message per cell of a selected parameter that does not parse."""
        out = []
        for key in self.checked_keys():
            i = self.row_of(key)
            for column in (VALUE, LR, MIN, MAX):
                problem = self._problem(i, column)
                if problem:
                    out.append(f"{key}: {COLUMNS[column].lower()}: {problem}")
        return out

    def specs(self) -> list[pb.ParameterSpec]:
        """A ParameterSpec per selected row, with only the fields that differ from the
        defaults. Raises ValueError (naming key and column) if a cell does not parse."""
        problems = self.errors()
        if problems:
            raise ValueError("; ".join(problems))
        out = []
        for key in self.checked_keys():
            i = self.row_of(key)
            row, p = self.rows[i], self.rows[i].parameter
            spec = pb.ParameterSpec(key=key)
            for column, default, name in ((LR, p.default_learning_rate, "learning_rate"),
                                          (MIN, p.min, "min"), (MAX, p.max, "max")):
                number = parse_values(self.table.item(i, column).text())[0]
                if not _same(number, default):
                    setattr(spec, name, number)
            if row.editable:
                values = parse_values(self.table.item(i, VALUE).text())
                if not all(_same(a, b) for a, b in zip(values, p.value)):
                    spec.initial_value.extend(values)
            elif row.initial is not None:
                spec.initial_value.extend(row.initial)
            elif row.initial_blob:
                spec.initial_blob = row.initial_blob
            out.append(spec)
        return out

    def apply_specs(self, specs: Iterable[pb.ParameterSpec]) -> list[str]:
        """Shows an earlier job's choices (to edit and restart it); returns unknown keys.

        Only the given keys end up selected; their learning rates, ranges and start values
        replace the defaults in the cells.
        """
        for i in range(len(self.rows)):
            self.table.item(i, OPT).setCheckState(Qt.CheckState.Unchecked)
        unknown = []
        for spec in specs:
            try:
                i = self.row_of(spec.key)
            except KeyError:
                unknown.append(spec.key)
                continue
            self.table.item(i, OPT).setCheckState(Qt.CheckState.Checked)
            for column, name in ((LR, "learning_rate"), (MIN, "min"), (MAX, "max")):
                if spec.HasField(name):
                    self.table.item(i, column).setText(format_float(getattr(spec, name)))
            if spec.initial_value:
                self.set_initial(spec.key, spec.initial_value)
            elif spec.initial_blob:
                self.rows[i].initial_blob = spec.initial_blob
                self.table.item(i, VALUE).setText("from the earlier job (.npy)")
        return unknown

    # -- values of the iteration or result being shown -----------------------------------------

    def show_current(self, values: Iterable[pb.ParameterValue]) -> None:
        """Fills the "Current" column: the iterate being optimized, or a result's values
        with their standard errors (0.41 +- 0.003)."""
        self._filling = True
        try:
            index = {row.parameter.key: i for i, row in enumerate(self.rows)}
            for v in values:
                i = index.get(v.key)
                if i is None:
                    continue
                item = self.table.item(i, CURRENT)
                item.setText("(large: see export)" if not v.value else
                             workflow.verdict(v.value, v)
                             if len(v.standard_error) else format_values(v.value))
                if self.rows[i].parameter.kind == pb.PARAMETER_KIND_RGB and len(v.value) >= 3:
                    item.setIcon(swatch(v.value))
        finally:
            self._filling = False

    def clear_current(self) -> None:
        self._filling = True
        try:
            for i in range(len(self.rows)):
                item = self.table.item(i, CURRENT)
                item.setText("")
                item.setIcon(QIcon())
        finally:
            self._filling = False

    # -- internals -----------------------------------------------------------------------------

    def _problem(self, i: int, column: int) -> str | None:
        row = self.rows[i]
        text = self.table.item(i, column).text()
        if column == VALUE and not row.editable:
            return None
        try:
            values = parse_values(text)
        except ValueError as exc:
            return str(exc)
        want = len(row.parameter.value) if column == VALUE else 1
        if len(values) != want:
            return f"'{text}' has {len(values)} numbers, expected {want}"
        if column != VALUE and any(math.isnan(v) for v in values):
            return "NaN is not allowed"
        return None

    def _item_changed(self, item: QTableWidgetItem) -> None:
        if self._filling:
            return
        i, column = item.row(), item.column()
        if i >= len(self.rows):
            return
        self._filling = True
        try:
            if column in (VALUE, LR, MIN, MAX):
                problem = self._problem(i, column)
                item.setBackground(QBrush(INVALID) if problem else QBrush())
                item.setToolTip(problem or "")
                if (column == VALUE and not problem and self.rows[i].editable
                        and self.rows[i].parameter.kind == pb.PARAMETER_KIND_RGB):
                    item.setIcon(swatch(parse_values(item.text())))
        finally:
            self._filling = False
        self._update_summary()
        self.changed.emit()

    def _apply_filter(self, text: str) -> None:
        needle = text.strip().lower()
        for i, row in enumerate(self.rows):
            self.table.setRowHidden(i, bool(needle) and needle not in row.parameter.key.lower())

    def _update_summary(self) -> None:
        if not self.rows:
            self.summary.setText("")
            return
        self.summary.setText(f"{len(self.checked_keys())} of {len(self.rows)} selected")


def _readonly(text: str, tooltip: str = "") -> QTableWidgetItem:
    item = QTableWidgetItem(text)
    item.setFlags(Qt.ItemFlag.ItemIsEnabled | Qt.ItemFlag.ItemIsSelectable)
    if tooltip:
        item.setToolTip(tooltip)
    return item


def _key_tooltip(p: pb.Parameter) -> str:
    tip = p.key
    if p.discontinuous:
        tip += ("\nGeometry/transform: gradients need a projective integrator "
                "(the daemon picks prb_projective when this is selected).")
    return tip


def _same(a: float, b: float) -> bool:
    """Equal as float32 values travel: a cell showing the default is not an override."""
    if math.isinf(a) or math.isinf(b):
        return a == b
    return mc.short_float(a) == mc.short_float(b) or math.isclose(a, b, rel_tol=1e-6,
                                                                   abs_tol=1e-9)

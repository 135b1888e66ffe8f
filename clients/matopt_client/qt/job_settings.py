"""The job's settings besides parameters and references: loss, schedule, iterations, spp,
min error, how sensors step, clamping, fitting the references' exposure. The fields start
at "daemon default": what is left so is not sent, and the daemon fills it in (the job's
spec, shown with the job, says what it applied); this client keeps no copy of the daemon's
defaults. The losses, schedules and sensor modes offered are the ones the daemon announces
(ServerInfo), filled in on connecting: a loss the daemon gains shows up without a change
here.
"""

from __future__ import annotations

from typing import Sequence

from PySide6.QtCore import QLocale, Qt
from PySide6.QtGui import QDoubleValidator
from PySide6.QtWidgets import (QCheckBox, QComboBox, QFormLayout, QLineEdit, QSpinBox,
                               QWidget)

from matopt_client import workflow
from matopt_api.v1 import matopt_pb2 as pb

DEFAULT = "daemon default"  # a field left to the daemon: not sent


def _fill(combo: QComboBox, names: Sequence[str], tips: dict[str, str] | None = None) -> None:
    """The daemon's names as the items' data, after DEFAULT (no data), shown with spaces for
    underscores (except losses, which read as the CLI's --loss); the selection is kept when
    still offered."""
    current = combo.currentData()
    combo.clear()
    combo.addItem(DEFAULT, None)
    for name in names:
        combo.addItem(name if tips is not None else name.replace("_", " "), name)
        if tips and name in tips:
            combo.setItemData(combo.count() - 1, tips[name], Qt.ItemDataRole.ToolTipRole)
    _select(combo, current)


def _select(combo: QComboBox, name: str | None) -> None:
    """Selects the item of ``name`` (the daemon's name, or as shown); one not offered
    leaves the selection as it is."""
    if name is None:
        return
    index = combo.findData(name)
    index = index if index >= 0 else combo.findText(name)
    if index >= 0:
        combo.setCurrentIndex(index)


def _unset_spin_box(most: int) -> QSpinBox:
    """A count from 1 to ``most``, or 0 shown as DEFAULT."""
    box = QSpinBox()
    box.setRange(0, most)
    box.setSpecialValueText(DEFAULT)
    return box


class JobSettingsForm(QWidget):
    """A form whose values are a ``workflow.JobSettings``."""

    def __init__(self, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        form = QFormLayout(self)
        form.setContentsMargins(0, 0, 0, 0)
        self.loss = QComboBox()
        # Sized for short names: the longest loss name would otherwise widen the whole form.
        self.loss.setSizeAdjustPolicy(
            QComboBox.SizeAdjustPolicy.AdjustToMinimumContentsLengthWithIcon)
        self.loss.setMinimumContentsLength(12)
        self.schedule = QComboBox()
        self.schedule.setToolTip("cosine: the learning rate decays to a tenth over the job, "
                                 "so the last iterate settles")
        self.iterations = _unset_spin_box(1_000_000)
        self.spp = _unset_spin_box(65536)
        self.spp.setToolTip("samples per pixel of each optimization step")
        self.min_error = QLineEdit()
        self.min_error.setPlaceholderText(DEFAULT)
        validator = QDoubleValidator(0.0, 1e30, 12)
        validator.setNotation(QDoubleValidator.Notation.ScientificNotation)
        validator.setLocale(QLocale.c())  # "0.001" everywhere, as the CLI and the API write it
        self.min_error.setValidator(validator)
        self.min_error.setToolTip("stop once the loss (mean over sensors) is below this; "
                                  "0 runs all iterations")
        self.sensor_mode = QComboBox()
        self.sensor_mode.setToolTip("accumulate: one step per iteration from all sensors' "
                                    "gradients; step per sensor: one step per sensor per "
                                    "iteration, as the thesis tool did")
        self.clamp = QCheckBox("Clamp to [0, 1]")
        self.clamp.setToolTip("compare render and reference clamped to [0, 1] (LDR); off, "
                              "highlights and HDR references keep their gradients")
        form.addRow("Loss", self.loss)
        form.addRow("Schedule", self.schedule)
        form.addRow("Iterations", self.iterations)
        form.addRow("Samples per pixel", self.spp)
        form.addRow("Min error", self.min_error)
        form.addRow("Sensors", self.sensor_mode)
        # Photographs rarely share the scene's units: an unknown exposure and white balance
        # would otherwise be "explained" by wrong reflectances.
        self.fit_exposure = QCheckBox("Fit exposure")
        self.fit_exposure.setToolTip("fit an RGB gain per reference (a photograph's unknown "
                                     "exposure and white balance) with the parameters; keep "
                                     "something of known brightness fixed (a white surface, "
                                     "the light), else gain and reflectances trade off")
        form.addRow("", self.clamp)
        form.addRow("", self.fit_exposure)

    def set_choices(self, choices: workflow.Choices) -> None:
        """The names this daemon accepts (from its ServerInfo, on connecting)."""
        _fill(self.loss, choices.losses, choices.loss_titles)
        _fill(self.schedule, choices.schedules)
        _fill(self.sensor_mode, choices.sensor_modes)

    def set_values(self, loss: str | None = None, iterations: int | None = None,
                   spp: int | None = None, min_error: float | None = None,
                   schedule: str | None = None, sensor_mode: str | None = None,
                   clamp: bool | None = None, fit_exposure: bool | None = None) -> None:
        """Sets the given fields (tests and scripts; the user types into the form)."""
        _select(self.sensor_mode, sensor_mode)
        if clamp is not None:
            self.clamp.setChecked(clamp)
        if fit_exposure is not None:
            self.fit_exposure.setChecked(fit_exposure)
        _select(self.loss, loss)
        _select(self.schedule, schedule)
        if iterations is not None:
            self.iterations.setValue(iterations)
        if spp is not None:
            self.spp.setValue(spp)
        if min_error is not None:
            self.min_error.setText(f"{min_error:g}")

    def values(self) -> workflow.JobSettings:
        """The form's settings; those left at DEFAULT are None. ValueError for a min error
        that is no number."""
        text = self.min_error.text().strip()
        try:
            min_error = float(text) if text else None
        except ValueError:
            raise ValueError(f"min error '{text}' is not a number") from None
        return workflow.JobSettings(
            loss=self.loss.currentData(), schedule=self.schedule.currentData(),
            sensor_mode=self.sensor_mode.currentData(),
            iterations=self.iterations.value() or None, spp=self.spp.value() or None,
            min_error=min_error, clamp=self.clamp.isChecked(),
            fit_exposure=self.fit_exposure.isChecked())

    def apply(self, spec: pb.JobSpec) -> None:
        """Shows an earlier job's settings (the daemon returns them with defaults filled in)."""
        settings = workflow.settings_of(spec)
        self.set_values(loss=settings.loss, iterations=settings.iterations, spp=settings.spp,
                        min_error=settings.min_error, schedule=settings.schedule,
                        sensor_mode=settings.sensor_mode, clamp=settings.clamp,
                        fit_exposure=settings.fit_exposure)

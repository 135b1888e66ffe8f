"""The job's settings besides parameters and references: loss, schedule, iterations, spp,
min error, how sensors step, clamping. The fields start at the daemon's documented defaults
(MSE, 100 iterations, 16 spp, min error 0.001, cosine decay) so that what the
user sees is what runs. The losses offered are the API's Loss enum, so a loss the daemon
gains shows up here without a change to this file (named after the enum, lowercase, as the
CLI names them).
"""

from __future__ import annotations

from PySide6.QtCore import QLocale, Qt
from PySide6.QtGui import QDoubleValidator
from PySide6.QtWidgets import (QCheckBox, QComboBox, QFormLayout, QLineEdit, QSpinBox,
                               QWidget)

from matopt_api import enums
from matopt_api.v1 import matopt_pb2 as pb

LOSSES = {name: enums.parse(pb.Loss, name) for name in enums.short_names(pb.Loss)}
SCHEDULES = {"cosine": pb.SCHEDULE_COSINE, "constant": pb.SCHEDULE_CONSTANT}
SENSOR_MODES = {"accumulate": pb.SENSOR_MODE_ACCUMULATE, "step per sensor": pb.SENSOR_MODE_STEP_PER_SENSOR}
LOSS_TIPS = {
    "mse": "mean squared error",
    "dual_buffer": "two independent renders, mean((a - ref)(b - ref)): render noise does not "
                   "bias the optimum (Deng et al. 2022); a single estimate can be negative",
    "brightness_independent_mse": "MSE after dividing render and reference by their own means: "
                                  "matches colour and shading, not overall brightness",
    "mae": "mean absolute error (L1)",
    "multiscale_mse": "MSE summed over an image pyramid (full, 1/2, 1/4, ...)",
}


class JobSettings(QWidget):
    """A form whose values fill the scalar fields of a JobSpec."""

    def __init__(self, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        form = QFormLayout(self)
        form.setContentsMargins(0, 0, 0, 0)
        self.loss = QComboBox()
        self.loss.addItems(list(LOSSES))
        for i, name in enumerate(LOSSES):
            if name in LOSS_TIPS:
                self.loss.setItemData(i, LOSS_TIPS[name], Qt.ItemDataRole.ToolTipRole)
        # Sized for short names: the longest loss name would otherwise widen the whole form.
        self.loss.setSizeAdjustPolicy(
            QComboBox.SizeAdjustPolicy.AdjustToMinimumContentsLengthWithIcon)
        self.loss.setMinimumContentsLength(12)
        self.schedule = QComboBox()
        self.schedule.addItems(list(SCHEDULES))
        self.schedule.setToolTip("cosine: the learning rate decays to a tenth over the job, "
                                 "so the last iterate settles")
        self.iterations = QSpinBox()
        self.iterations.setRange(1, 1_000_000)
        self.iterations.setValue(100)
        self.spp = QSpinBox()
        self.spp.setRange(1, 65536)
        self.spp.setValue(16)
        self.spp.setToolTip("samples per pixel of each optimization step")
        self.min_error = QLineEdit("0")
        validator = QDoubleValidator(0.0, 1e30, 12)
        validator.setNotation(QDoubleValidator.Notation.ScientificNotation)
        validator.setLocale(QLocale.c())  # "0.001" everywhere, as the CLI and the API write it
        self.min_error.setValidator(validator)
        self.min_error.setToolTip("stop once the loss (mean over sensors) is below this; "
                                  "0 (the default) runs all iterations")
        self.sensor_mode = QComboBox()
        self.sensor_mode.addItems(list(SENSOR_MODES))
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
        form.addRow("", self.clamp)

    def set_values(self, loss: str | None = None, iterations: int | None = None,
                   spp: int | None = None, min_error: float | None = None,
                   schedule: str | None = None, sensor_mode: str | None = None,
                   clamp: bool | None = None) -> None:
        """Sets the given fields (tests and scripts; the user types into the form)."""
        if sensor_mode is not None:
            self.sensor_mode.setCurrentText(sensor_mode)
        if clamp is not None:
            self.clamp.setChecked(clamp)
        if loss is not None:
            self.loss.setCurrentText(loss)
        if schedule is not None:
            self.schedule.setCurrentText(schedule)
        if iterations is not None:
            self.iterations.setValue(iterations)
        if spp is not None:
            self.spp.setValue(spp)
        if min_error is not None:
            self.min_error.setText(f"{min_error:g}")

    def fill(self, spec: pb.JobSpec) -> None:
        """Writes the form into ``spec``. Raises ValueError for a min error that is no number."""
        try:
            min_error = float(self.min_error.text())
        except ValueError:
            raise ValueError(f"min error '{self.min_error.text()}' is not a number") from None
        spec.loss = LOSSES[self.loss.currentText()]
        spec.schedule = SCHEDULES[self.schedule.currentText()]
        spec.iterations = self.iterations.value()
        spec.spp = self.spp.value()
        spec.min_error = min_error
        spec.sensor_mode = SENSOR_MODES[self.sensor_mode.currentText()]
        spec.clamp = self.clamp.isChecked()

    def apply(self, spec: pb.JobSpec) -> None:
        """Shows an earlier job's settings (the daemon returns them with defaults filled in)."""
        names = {v: k for k, v in LOSSES.items()}
        self.loss.setCurrentText(names.get(spec.loss, "mse"))
        modes = {v: k for k, v in SENSOR_MODES.items()}
        self.sensor_mode.setCurrentText(modes.get(spec.sensor_mode, "accumulate"))
        self.clamp.setChecked(spec.clamp)
        schedules = {v: k for k, v in SCHEDULES.items()}
        self.schedule.setCurrentText(schedules.get(spec.schedule, "cosine"))
        if spec.HasField("iterations"):
            self.iterations.setValue(spec.iterations)
        if spec.HasField("spp"):
            self.spp.setValue(spec.spp)
        if spec.HasField("min_error"):
            self.min_error.setText(f"{spec.min_error:g}")

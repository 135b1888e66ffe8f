"""The right half of the window: one job's progress, controls, images and loss plot, and
what the numbers alone do not say: each parameter's error against the ground truth (a job
given one) and the exposure gains fitted to photographs (a job with fit exposure).

Only widgets live here; what happens on a click is the main window's business (it owns the
connection and the job), so this panel can show any job: one just started, one opened from
the list, or one that finished long ago.
"""

from __future__ import annotations

from typing import Iterable, Sequence

from PySide6.QtWidgets import (QButtonGroup, QCheckBox, QComboBox, QGridLayout, QHBoxLayout,
                               QLabel, QProgressBar, QPushButton, QRadioButton, QSplitter,
                               QVBoxLayout, QWidget)
from PySide6.QtCore import Qt

from matopt_client import client as mc
from matopt_client import workflow
from matopt_client.qt.images import ImagePane
from matopt_client.qt.plot import LossPlot
from matopt_api.v1 import matopt_pb2 as pb

RUNNING_STATES = (pb.JOB_STATE_QUEUED, pb.JOB_STATE_RUNNING)


class JobView(QWidget):
    """Header (job, state, numbers), progress bar, pause/resume/cancel, sensor and best/last
    choice, reference and render side by side, the loss plot, and export."""

    def __init__(self, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        layout = QVBoxLayout(self)
        layout.setContentsMargins(4, 0, 0, 0)

        self.header = QLabel("<b>No job</b> — open a scene, pick parameters and references, "
                             "then Start; or open a job from the list")
        self.header.setWordWrap(True)
        self.header.setTextInteractionFlags(Qt.TextInteractionFlag.TextSelectableByMouse)
        layout.addWidget(self.header)
        self.numbers = QLabel("")
        layout.addWidget(self.numbers)
        self.notes = QLabel("")
        self.notes.setWordWrap(True)
        self.notes.setStyleSheet("QLabel { color: #555; }")
        self.notes.setToolTip("what the daemon chose for this job, and why")
        self.notes.hide()
        layout.addWidget(self.notes)
        self.truth_errors = _detail("each parameter's error against the job's ground truth "
                                    "(root mean square, peak signal-to-noise ratio, and for "
                                    "textures the correlation per channel)")
        layout.addWidget(self.truth_errors)
        self.gains = _detail("render × gain is what the loss compares with each reference")
        layout.addWidget(self.gains)

        row = QHBoxLayout()
        self.progress = QProgressBar()
        self.progress.setRange(0, 1)
        self.progress.setValue(0)
        self.progress.setFormat("%v / %m iterations")
        self.pause_button = QPushButton("Pause")
        self.resume_button = QPushButton("Resume")
        self.cancel_button = QPushButton("Cancel")
        self.cancel_button.setToolTip("stop at the next iteration; results so far are kept")
        row.addWidget(self.progress, 1)
        for button in (self.pause_button, self.resume_button, self.cancel_button):
            button.setEnabled(False)
            row.addWidget(button)
        layout.addLayout(row)

        choices = QHBoxLayout()
        choices.addWidget(QLabel("Sensor"))
        self.sensor = QComboBox()
        self.sensor.setMinimumContentsLength(12)
        choices.addWidget(self.sensor)
        choices.addSpacing(12)
        self.best_radio = QRadioButton("Best")
        self.best_radio.setToolTip("the iteration with the lowest loss")
        self.last_radio = QRadioButton("Last")
        self.last_radio.setToolTip("the final iterate (what the decaying learning rate settles)")
        self.best_radio.setChecked(True)
        self.which_group = QButtonGroup(self)
        self.which_group.addButton(self.best_radio)
        self.which_group.addButton(self.last_radio)
        choices.addWidget(self.best_radio)
        choices.addWidget(self.last_radio)
        choices.addSpacing(12)
        choices.addWidget(QLabel("Render"))
        self.role = QComboBox()
        self.role.addItems(["optimized", "initial", "error"])
        self.role.setItemData(2, "|optimized − reference|, per pixel",
                              Qt.ItemDataRole.ToolTipRole)
        choices.addWidget(self.role)
        self.live = QCheckBox("Live preview")
        self.live.setChecked(True)
        self.live.setToolTip("while the job runs, render the latest iterate at low spp every "
                             "few seconds (less often when a render is slow)")
        choices.addWidget(self.live)
        choices.addStretch(1)
        layout.addLayout(choices)

        splitter = QSplitter(Qt.Orientation.Vertical)
        images = QWidget()
        grid = QGridLayout(images)
        grid.setContentsMargins(0, 0, 0, 0)
        self.reference = ImagePane("Reference")
        self.render = ImagePane("Render")
        grid.addWidget(self.reference, 0, 0)
        grid.addWidget(self.render, 0, 1)
        splitter.addWidget(images)
        self.plot = LossPlot()
        splitter.addWidget(self.plot)
        splitter.setStretchFactor(0, 3)
        splitter.setStretchFactor(1, 2)
        layout.addWidget(splitter, 1)

        bottom = QHBoxLayout()
        self.result_label = QLabel("")
        self.use_result_button = QPushButton("Use as start values")
        self.use_result_button.setToolTip("copy the shown result's values into the parameter "
                                          "table, to continue from them in a new job")
        self.export_button = QPushButton("Export…")
        self.export_button.setToolTip("write parameters.json, the images and history.csv to a "
                                      "folder (as 'matopt job export')")
        self.estimate_button = QPushButton("Standard errors")
        self.estimate_button.setToolTip("estimate now how sure each value of the shown "
                                         "iteration is (a paused job; an ended job's results "
                                         "show them already)")
        self.use_result_button.setEnabled(False)
        self.export_button.setEnabled(False)
        self.estimate_button.setEnabled(False)
        bottom.addWidget(self.result_label, 1)
        bottom.addWidget(self.estimate_button)
        bottom.addWidget(self.use_result_button)
        bottom.addWidget(self.export_button)
        layout.addLayout(bottom)

    # -- helpers for the window ----------------------------------------------------------------

    def which(self) -> str:
        return "last" if self.last_radio.isChecked() else "best"

    def set_sensors(self, sensors: Sequence[pb.Sensor]) -> None:
        """Fills the sensor choice, keeping the current sensor where it still exists."""
        current = self.sensor_index()
        self.sensor.blockSignals(True)
        self.sensor.clear()
        for s in sensors:
            label = f"{s.index}" + (f" '{s.id}'" if s.id else "") + f" ({s.width}×{s.height})"
            self.sensor.addItem(label, s.index)
        position = max(0, self.sensor.findData(current)) if current is not None else 0
        self.sensor.setCurrentIndex(position if sensors else -1)
        self.sensor.blockSignals(False)

    def sensor_index(self) -> int | None:
        data = self.sensor.currentData()
        return int(data) if data is not None else None

    def show_job(self, job: pb.Job | None) -> None:
        """Header, numbers, progress and which buttons apply, from the job's state."""
        if job is None:
            self.header.setText("<b>No job</b>")
            self.numbers.setText("")
            self.progress.setRange(0, 1)
            self.progress.setValue(0)
            for button in (self.pause_button, self.resume_button, self.cancel_button):
                button.setEnabled(False)
            self.notes.hide()
            return
        text = f"<b>{job.name}</b> — {workflow.state_text(job)}"
        if job.integrator:
            text += f" — {job.integrator}"
        if job.state == pb.JOB_STATE_FAILED and job.error:
            text += f"<br><span style='color:#a00'>{_escape(job.error)}</span>"
        if job.resumed_from:
            text += f"<br>resumed from {job.resumed_from}"
        # What it runs with, the daemon's defaults filled in: the form may have left them.
        text += f"<br><small>{_escape(workflow.applied(job.spec))}</small>"
        self.header.setText(text)
        self.notes.setText("; ".join(job.notes))
        self.notes.setVisible(bool(job.notes))
        total = max(job.spec.iterations, 1)
        self.progress.setRange(0, total)
        self.progress.setValue(min(job.iteration, total))
        self.pause_button.setEnabled(job.state in RUNNING_STATES)
        self.resume_button.setEnabled(job.state in (pb.JOB_STATE_PAUSED, pb.JOB_STATE_INTERRUPTED))
        self.cancel_button.setEnabled(job.state not in mc.TERMINAL_STATES)
        best = workflow.best(job)
        self.set_numbers(job.iteration, job.loss if job.iteration else None,
                         best[1] if best else None, job.elapsed_seconds)

    def show_truth_errors(self, record: pb.IterationRecord | None) -> None:
        """The errors of ``record`` (the latest iteration); hidden for a job without ground
        truth."""
        if record is None:
            _show(self.truth_errors, "", [])
            return
        _show(self.truth_errors, f"Error against the truth at iteration {record.iteration}:",
              [f"{e.key}: {workflow.parameter_error(e)}" for e in record.errors])

    def show_gains(self, gains: Iterable[pb.ReferenceGain], where: str = "") -> None:
        """The fitted exposure gains of the iteration ``where`` names ("best iteration 41");
        hidden for a job that fits none."""
        lines = [f"{k}: {v}" for k, v in workflow.gain_fields(gains).items()]
        _show(self.gains, f"Fitted exposure, {where}:", lines)

    def set_numbers(self, iteration: int, loss: float | None, best: float | None,
                    seconds: float) -> None:
        parts = [f"iteration {iteration}"]
        if loss is not None:
            parts.append(f"loss {loss:.4g}")
        if best is not None:
            parts.append(f"best {best:.4g}")
        parts.append(f"{seconds:.1f} s")
        self.numbers.setText("   ".join(parts))


def _detail(tip: str) -> QLabel:
    label = QLabel("")
    label.setTextFormat(Qt.TextFormat.PlainText)
    label.setWordWrap(True)
    label.setTextInteractionFlags(Qt.TextInteractionFlag.TextSelectableByMouse)
    label.setToolTip(tip)
    label.hide()
    return label


def _show(label: QLabel, title: str, lines: list[str]) -> None:
    """A heading and its lines as plain text; the label hidden when there are none."""
    label.setText("\n".join([title, *(f"  {line}" for line in lines)]) if lines else "")
    label.setVisible(bool(lines))


def _escape(text: str) -> str:
    return text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")

"""The setup of the next job (the window's middle pane): the scene, its parameter table, one
reference per sensor, the optimization settings and *Start*.

Besides its fields it holds what a restart keeps without showing a field for it: the spec of
the job opened or started last (seed, film height, ground truth, ...), and the result the
next job continues from.
"""

from __future__ import annotations

from PySide6.QtCore import Qt
from PySide6.QtWidgets import (QGroupBox, QHBoxLayout, QLabel, QPushButton, QToolButton,
                               QVBoxLayout, QWidget)

from matopt_client.qt.job_settings import JobSettingsForm
from matopt_client.qt.params_table import ParamsTable
from matopt_client.qt.references import ReferenceList
from matopt_api.v1 import matopt_pb2 as pb

NO_SCENE = "<b>No scene</b> — Open scene… or Cornell box"


class SetupPanel(QWidget):
    """Scene label, parameter table, references, settings form and Start button."""

    def __init__(self, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        column = QVBoxLayout(self)
        column.setContentsMargins(0, 0, 4, 0)
        self.scene_label = QLabel(NO_SCENE)
        self.scene_label.setTextInteractionFlags(Qt.TextInteractionFlag.TextSelectableByMouse)
        column.addWidget(self.scene_label)
        self.params = ParamsTable()
        column.addWidget(self.params, 1)
        lower = QHBoxLayout()
        refs_box = QGroupBox("References (one per sensor)")
        refs_layout = QVBoxLayout(refs_box)
        self.references = ReferenceList()
        refs_layout.addWidget(self.references)
        lower.addWidget(refs_box, 3)
        settings_box = QGroupBox("Optimization")
        settings_layout = QVBoxLayout(settings_box)
        self.settings = JobSettingsForm()
        settings_layout.addWidget(self.settings)
        self.kept_label = QLabel("")
        self.kept_label.setWordWrap(True)
        self.kept_label.setStyleSheet("QLabel { color: #555; }")
        self.kept_label.setToolTip("settings of the opened job that this window has no field "
                                   "for; a restart keeps them")
        self.kept_label.hide()
        settings_layout.addWidget(self.kept_label)
        continue_row = QHBoxLayout()
        self.continue_label = QLabel("")
        self.continue_label.setWordWrap(True)
        self.continue_label.setStyleSheet("QLabel { color: #0d3c6e; }")
        self.continue_clear = QToolButton()
        self.continue_clear.setText("✕")
        self.continue_clear.setAutoRaise(True)
        self.continue_clear.setToolTip("start from the table's values and the scene's instead")
        self.continue_clear.clicked.connect(lambda: self.set_initial_from(None))
        continue_row.addWidget(self.continue_label, 1)
        continue_row.addWidget(self.continue_clear)
        settings_layout.addLayout(continue_row)
        self.start_button = QPushButton("Start")
        self.start_button.setDefault(True)
        settings_layout.addWidget(self.start_button)
        lower.addWidget(settings_box, 2)
        column.addLayout(lower)

        # The spec of the job opened or started last: a restart keeps whatever the setup does
        # not show (seed, resolution, ground truth, ...) instead of silently dropping it.
        self.base_spec: pb.JobSpec | None = None
        self.initial_from: tuple[str, int] | None = None  # (job, pb.Which) to continue from
        self.set_initial_from(None)

    def show_scene(self, scene: pb.Scene | None) -> None:
        """The scene's name, sensors and overrides above the table."""
        if scene is None:
            self.scene_label.setText(NO_SCENE)
            return
        overrides = ", ".join(f"{k}={v}" for k, v in sorted(scene.overrides.items()))
        count = len(scene.sensors)
        sensors = f"{count} sensor{'' if count == 1 else 's'}"
        self.scene_label.setText(f"<b>{scene.display_name}</b> ({scene.name}) — {sensors}"
                                 + (f" — {overrides}" if overrides else ""))
        self.scene_label.setToolTip(scene.main_file or "built-in Cornell box")

    def set_base_spec(self, spec: pb.JobSpec | None, source: str = "") -> None:
        """The spec a restart starts from; what it sets beyond the form is listed."""
        self.base_spec = spec
        kept = inherited(spec) if spec is not None else []
        self.kept_label.setText(f"Also kept from {source}: {', '.join(kept)}" if kept else "")
        self.kept_label.setVisible(bool(kept))

    def set_initial_from(self, source: tuple[str, int] | None) -> None:
        """The result (job, pb.Which) the next job continues from, or None."""
        self.initial_from = source
        if source is not None:
            which = "last" if source[1] == pb.WHICH_LAST else "best"
            self.continue_label.setText(f"Continues from {source[0]} ({which}) where the "
                                        f"table sets no start value")
        self.continue_label.setVisible(source is not None)
        self.continue_clear.setVisible(source is not None)


def inherited(spec: pb.JobSpec) -> list[str]:
    """The settings of ``spec`` that the setup has no field for and that differ from the
    defaults, in words (what a restart keeps without showing it)."""
    out = []
    if spec.seed:
        out.append(f"seed {spec.seed}")
    if spec.HasField("learning_rate"):
        out.append(f"default learning rate {spec.learning_rate:g}")
    if spec.film_height:
        out.append(f"film height {spec.film_height} px")
    if spec.ground_truth:
        out.append(f"ground truth of {len(spec.ground_truth)} parameter(s)")
    if spec.image_error_every:
        out.append(f"image error every {spec.image_error_every} iterations")
    return out

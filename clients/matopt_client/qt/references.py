"""One reference image per sensor: which photo (or target render) each camera should match.

Images chosen together map to the sensors in file-name order (``ref0.png, ref1.png, ...``,
numbers compared as numbers), which is how people name per-camera shots; a count that differs
from the scene's sensor count is refused at once, naming both numbers, rather than later by
the daemon. A single sensor's image can also be set on its own (double-click its row); then
only the sensors with an image are optimized against.

A photograph shows more than the scene models (background, fixtures, blown-out highlights):
*Mask* on the selected sensor's row gives its reference a mask image (black leaves a pixel out
of the loss, white counts it) or uses the image's own alpha channel, as ``matopt job start
--mask`` does. A new image for a sensor drops its mask: a mask belongs to one photograph.

A job opened from the server (to edit and restart it) keeps its references, masks included,
as blobs that are already there, so a restart uploads nothing.
"""

from __future__ import annotations

import os
import re
from typing import Sequence

from PySide6.QtCore import Signal
from PySide6.QtWidgets import (QFileDialog, QHBoxLayout, QListWidget, QListWidgetItem, QMenu,
                               QPushButton, QVBoxLayout, QWidget)

from matopt_client.workflow import ReferenceFile, is_blob, reference_files, reference_label
from matopt_api.v1 import matopt_pb2 as pb

IMAGE_FILTER = "Images (*.png *.jpg *.jpeg *.exr);;All files (*)"


def natural_key(path: str) -> list:
    """``ref2.png`` before ``ref10.png``."""
    name = os.path.basename(path).lower()
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", name)]


def plural(n: int, word: str) -> str:
    return f"{n} {word}{'' if n == 1 else 's'}"


def count_mismatch(images: int, sensors: int) -> str:
    """The message for a wrong number of images, naming both numbers."""
    return (f"{plural(images, 'reference image')} chosen, but the scene has "
            f"{plural(sensors, 'sensor')}: choose one image per sensor, in sensor order "
            f"(or double-click a sensor to set its image alone)")


class ReferenceList(QWidget):
    """The scene's sensors, each with its reference image (or none yet).

    ``problem(str)`` reports a refused choice; ``changed`` any accepted one.
    """

    changed = Signal()
    problem = Signal(str)

    def __init__(self, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.sensors: list[pb.Sensor] = []
        self.images: dict[int, ReferenceFile] = {}
        self.start_folder = ""
        layout = QVBoxLayout(self)
        layout.setContentsMargins(0, 0, 0, 0)
        self.list = QListWidget()
        self.list.setMaximumHeight(110)
        self.list.itemDoubleClicked.connect(lambda item: self.choose_one(self.list.row(item)))
        layout.addWidget(self.list)
        buttons = QHBoxLayout()
        self.load_button = QPushButton("Load references…")
        self.load_button.setToolTip("one image per sensor (PNG/JPEG as sRGB, OpenEXR as linear)")
        self.load_button.clicked.connect(self.choose_all)
        self.mask_button = self._mask_button()
        self.clear_button = QPushButton("Clear")
        self.clear_button.clicked.connect(self.clear)
        self.list.currentRowChanged.connect(lambda _: self._update_buttons())
        buttons.addWidget(self.load_button)
        buttons.addWidget(self.mask_button)
        buttons.addWidget(self.clear_button)
        buttons.addStretch(1)
        layout.addLayout(buttons)
        self._refresh()

    # -- content -------------------------------------------------------------------------------

    def set_sensors(self, sensors: Sequence[pb.Sensor]) -> None:
        """A new scene: its sensors, no images yet."""
        self.sensors = list(sensors)
        self.images = {}
        self._refresh()

    def clear(self) -> None:
        self.images = {}
        self._refresh()

    def set_files(self, paths: Sequence[str]) -> str | None:
        """Maps files to the sensors in name order; returns the problem if refused."""
        if not self.sensors:
            return self._refuse("open a scene before choosing its reference images")
        if len(paths) != len(self.sensors):
            return self._refuse(count_mismatch(len(paths), len(self.sensors)))
        ordered = sorted(paths, key=natural_key)
        self.images = {s.index: _local(s.index, p) for s, p in zip(self.sensors, ordered)}
        self._refresh()
        return None

    def set_file(self, sensor: int, path: str) -> None:
        self.images[sensor] = _local(sensor, path)
        self._refresh()

    def set_mask(self, sensor: int, mask: str | None) -> str | None:
        """``sensor``'s reference gets the mask image ``mask`` (a path or a blob; None: no
        mask image); returns the problem if that sensor has no reference yet."""
        name = os.path.basename(mask) if mask and not is_blob(mask) else ""
        return self._set_masking(sensor, mask=mask, mask_filename=name)

    def set_alpha_mask(self, sensor: int, on: bool = True) -> str | None:
        """Whether ``sensor``'s reference is masked by its own alpha channel (with a mask
        image as well, the two weights multiply)."""
        return self._set_masking(sensor, alpha_mask=on)

    def set_from_spec(self, references: Sequence[pb.Reference]) -> None:
        """An earlier job's references, kept as the blobs they already are on the server."""
        self.images = {}
        indices = [s.index for s in self.sensors]
        for n, ref in enumerate(reference_files(references)):
            if ref.sensor is None:  # in order, as the daemon maps them
                ref.sensor = indices[n] if n < len(indices) else n
            ref.filename = ref.filename or ref.image.rsplit("/", 1)[-1][:12]
            self.images[ref.sensor] = ref
        self._refresh()

    def reference(self, sensor: int) -> ReferenceFile | None:
        return self.images.get(sensor)

    def references(self) -> list[ReferenceFile]:
        return [self.images[i] for i in sorted(self.images)]

    # -- dialogs -------------------------------------------------------------------------------

    def choose_all(self) -> None:
        paths, _ = QFileDialog.getOpenFileNames(self, "Reference images, one per sensor",
                                                self.start_folder, IMAGE_FILTER)
        if paths:
            self.start_folder = os.path.dirname(paths[0])
            self.set_files(paths)

    def choose_one(self, row: int) -> None:
        if not 0 <= row < len(self.sensors):
            return
        sensor = self.sensors[row].index
        path, _ = QFileDialog.getOpenFileName(self, f"Reference image for sensor {sensor}",
                                              self.start_folder, IMAGE_FILTER)
        if path:
            self.start_folder = os.path.dirname(path)
            self.set_file(sensor, path)

    def choose_mask(self) -> None:
        """A mask image for the selected sensor's reference."""
        sensor = self.selected_sensor()
        if sensor is None:
            return
        path, _ = QFileDialog.getOpenFileName(
            self, f"Mask of sensor {sensor}'s reference (black: pixel left out)",
            self.start_folder, IMAGE_FILTER)
        if path:
            self.set_mask(sensor, path)

    def selected_sensor(self) -> int | None:
        row = self.list.currentRow()
        return self.sensors[row].index if 0 <= row < len(self.sensors) else None

    # -- internals -----------------------------------------------------------------------------

    def _mask_button(self) -> QPushButton:
        """*Mask* and its menu, acting on the selected row."""
        button = QPushButton("Mask")
        button.setToolTip("leave pixels of the selected sensor's reference out of the loss "
                          "(background, fixtures, blown-out highlights)")
        menu = QMenu(button)
        menu.addAction("Mask image…", self.choose_mask)
        self.alpha_action = menu.addAction("Its alpha channel")
        self.alpha_action.setCheckable(True)
        self.alpha_action.toggled.connect(self._alpha_toggled)
        menu.addAction("No mask", self._no_mask)
        button.setMenu(menu)
        return button

    def _alpha_toggled(self, on: bool) -> None:
        sensor = self.selected_sensor()
        ref = self.images.get(sensor) if sensor is not None else None
        if ref is not None and ref.alpha_mask != on:
            self.set_alpha_mask(sensor, on)

    def _no_mask(self) -> None:
        sensor = self.selected_sensor()
        if sensor is not None:
            self._set_masking(sensor, mask=None, mask_filename="", alpha_mask=False)

    def _set_masking(self, sensor: int, **fields) -> str | None:
        """Sets ReferenceFile ``fields`` of ``sensor``'s reference; the problem if it has
        none."""
        ref = self.images.get(sensor)
        if ref is None:
            return self._refuse(f"choose the reference image of sensor {sensor} before its mask")
        for name, value in fields.items():
            setattr(ref, name, value)
        self._refresh()
        return None

    def _update_buttons(self) -> None:
        sensor = self.selected_sensor()
        ref = self.images.get(sensor) if sensor is not None else None
        self.mask_button.setEnabled(ref is not None)
        self.alpha_action.setChecked(ref is not None and ref.alpha_mask)
        self.clear_button.setEnabled(bool(self.images))
        self.load_button.setEnabled(bool(self.sensors))

    def _refuse(self, message: str) -> str:
        self.problem.emit(message)
        return message

    def _refresh(self) -> None:
        row = self.list.currentRow()
        self.list.blockSignals(True)
        self.list.clear()
        if not self.sensors:
            self.list.addItem(QListWidgetItem("(open a scene first)"))
        for s in self.sensors:
            label = f"{s.index}" + (f" '{s.id}'" if s.id else "") + f" {s.width}×{s.height}: "
            image = self.images.get(s.index)
            if image is None:
                label += "— no image —"
            else:
                label += reference_label(image) + (" — on server" if image.on_server else "")
            item = QListWidgetItem(label)
            item.setToolTip("\n".join(f for f in (image.image, image.mask) if f) if image
                            else "double-click to choose this sensor's image")
            self.list.addItem(item)
        self.list.setCurrentRow(min(max(row, 0), self.list.count() - 1))
        self.list.blockSignals(False)
        self._update_buttons()
        self.changed.emit()


def _local(sensor: int, path: str) -> ReferenceFile:
    return ReferenceFile(image=str(path), sensor=sensor, filename=os.path.basename(path))

"""The window's scene: opening a scene file or the Cornell box (with the XML defaults of the
toolbar field), showing it in the setup, previewing it, and choosing its reference images.

A part of :class:`matopt_client.qt.app.MainWindow`, kept in a module of its own: its methods use the
window's panels and its ``_call`` (a daemon call off the GUI thread).
"""

from __future__ import annotations

import os
from typing import Callable, Sequence

from PySide6.QtWidgets import QFileDialog

from matopt_client import client as mc
from matopt_client import workflow
from matopt_client.qt.worker import CALL_TIMEOUT_S
from matopt_api.v1 import matopt_pb2 as pb

SCENE_PREVIEW_SPP = 16


def parse_overrides(text: str) -> dict[str, str]:
    """The XML-defaults field: ``"resx=64 resy=64"`` -> {"resx": "64", "resy": "64"}."""
    return workflow.parse_overrides(workflow.split_overrides(text))


def _create_scene(client: mc.Client, path: str | None, overrides: dict[str, str],
                  on_upload: Callable[[str, int], None]
                  ) -> tuple[pb.Scene, list[pb.Parameter]]:
    """Worker thread: creates the scene (``path`` None: the built-in Cornell box) and lists
    its parameters."""
    scene = workflow.create_scene(client, path, overrides, on_upload=on_upload)
    parameters = client.scenes.ListSceneParameters(
        pb.ListSceneParametersRequest(name=scene.name), timeout=CALL_TIMEOUT_S).parameters
    return scene, list(parameters)


class SceneControl:
    """Opening scenes and choosing references (a part of MainWindow)."""

    def open_scene_dialog(self) -> None:
        path, _ = QFileDialog.getOpenFileName(self, "Open a Mitsuba scene",
                                              self.store.folder("scene"),
                                              "Mitsuba scenes (*.xml);;All files (*)")
        if path:
            self.store.set_folder("scene", os.path.dirname(path))
            self.open_scene(path)

    def open_cornell_box(self, overrides: dict[str, str] | None = None) -> None:
        """The daemon's built-in scene: nothing to upload."""
        self.open_scene(None, overrides)

    def open_scene(self, path: str | os.PathLike | None,
                   overrides: dict[str, str] | None = None) -> None:
        """Uploads the scene's bundle and creates it (the Open scene action, past its dialog).

        ``overrides`` default to the XML-defaults field above the table.
        """
        if overrides is None:
            try:
                overrides = parse_overrides(self.overrides.text())
            except ValueError as exc:
                self.show_banner(f"XML defaults: {exc}", "warning")
                return
            self.store.set_value("scene/overrides", self.overrides.text())
        label = os.path.basename(os.fspath(path)) if path else "the Cornell box"
        self.status(f"loading {label}…")
        self.scene_label.setText(f"<b>Loading {label}…</b>")

        def note(file: str, size: int) -> None:  # worker thread: only a queued signal
            self._upload_note.emit(f"uploading {file} ({size / 1e6:.1f} MB)…")

        self._call(f"loading {label}",
                   lambda c: _create_scene(c, os.fspath(path) if path else None,
                                           overrides, note),
                   self._scene_loaded,
                   on_error=lambda exc: self.setup.show_scene(self.scene))

    def _scene_loaded(self, loaded: tuple[pb.Scene, list[pb.Parameter]]) -> None:
        scene, parameters = loaded
        self.show_job(None)  # a new scene starts a new setup: the old job stays in the list
        self._set_scene(scene, parameters)
        self.status(f"loaded {scene.display_name} as {scene.name}: {len(parameters)} "
                    f"parameters, {len(scene.sensors)} sensor(s)")
        if scene.warnings:
            self.show_banner("; ".join(scene.warnings), "warning")
        elif self.banner.level in ("warning", "info"):
            self.banner.clear()
        self._render_scene_preview()

    def _set_scene(self, scene: pb.Scene, parameters: list[pb.Parameter]) -> None:
        self.scene, self.parameters = scene, parameters
        self.setup.set_base_spec(None)
        self.setup.set_initial_from(None)
        self.params.set_parameters(parameters)
        self.references.set_sensors(scene.sensors)
        self.view.set_sensors(scene.sensors)
        self.previews.clear()
        self.setup.show_scene(self.scene)
        self._update_images()
        self._update_actions()

    def _sensor_changed(self) -> None:
        self._update_images()
        sensor = self.view.sensor_index()
        if self.job is None and sensor is not None and sensor not in self.previews:
            self._render_scene_preview()

    def _render_scene_preview(self) -> None:
        """The scene as loaded, for the chosen sensor: the user sees what they opened."""
        scene, sensor = self.scene, self.view.sensor_index()
        if scene is None or sensor is None:
            return

        def render(c: mc.Client):
            response = c.scenes.RenderScene(pb.RenderSceneRequest(
                name=scene.name, spp=SCENE_PREVIEW_SPP, sensors=[sensor]),
                timeout=CALL_TIMEOUT_S * 4)
            return self.cache.image(c, response.images[0].png_blob)

        def done(image) -> None:
            if self.scene is scene:
                self.previews[sensor] = (image, f"the scene as loaded ({SCENE_PREVIEW_SPP} spp)")
                self._update_images()

        self._call("rendering a preview", render, done)

    def choose_references(self) -> None:
        self.references.choose_all()
        self.store.set_folder("references", self.references.start_folder)

    def set_reference_files(self, paths: Sequence[str | os.PathLike]) -> str | None:
        """Maps images to the sensors; returns (and shows) the problem if the count is off."""
        problem = self.references.set_files([os.fspath(p) for p in paths])
        if problem is None and self.banner.level == "warning":
            self.banner.clear()
        return problem

    def _references_changed(self) -> None:
        self._update_images()
        self._update_actions()

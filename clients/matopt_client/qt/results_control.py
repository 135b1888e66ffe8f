"""The window's results: best or last iteration, the sensor shown, reference beside render
(result images, the reference file, or live previews while the job runs), taking a result as
the next start, and export.

A part of :class:`matopt_client.qt.app.MainWindow`, kept in a module of its own: its methods use the
window's panels and its ``_call`` (a daemon call off the GUI thread).
"""

from __future__ import annotations

import os
import time

import grpc
from PySide6.QtWidgets import QFileDialog

from matopt_client import client as mc
from matopt_client.export import export_job
from matopt_client.qt.images import read_image
from matopt_client.qt.worker import CALL_TIMEOUT_S, ESTIMATE_TIMEOUT_S
from matopt_api.v1 import matopt_pb2 as pb


class ResultsControl:
    """Showing and exporting a job's results (a part of MainWindow)."""

    def set_which(self, which: str) -> None:
        """"best" or "last": which iteration's result is shown (and exported)."""
        (self.view.last_radio if which == "last" else self.view.best_radio).setChecked(True)

    def set_sensor(self, sensor: int) -> None:
        position = self.view.sensor.findData(sensor)
        if position < 0:
            raise ValueError(f"no sensor {sensor}")
        self.view.sensor.setCurrentIndex(position)

    def _which_changed(self) -> None:
        if self.job is not None and (self.result is not None
                                     or self.job.state in mc.TERMINAL_STATES):
            self._fetch_result()

    def estimate_errors(self) -> None:
        """The shown iteration of a paused job with its standard errors, estimated now."""
        self._fetch_result(estimate=True)

    def _fetch_result(self, estimate: bool = False) -> None:
        if self.job is None:
            return
        name, which = self.job.name, self.view.which()

        def done(result: pb.JobResult) -> None:
            if self.job is None or self.job.name != name or self.view.which() != which:
                return
            self.result = result
            label = "best" if result.which != pb.WHICH_LAST else "last"
            self.view.result_label.setText(f"{label}: iteration {result.iteration}, "
                                           f"loss {result.loss:.4g}")
            self.view.result_label.setToolTip("\n".join(result.standard_error_notes))
            if estimate:
                self.status(f"standard errors of the {label} iteration estimated"
                            + (": " + result.standard_error_notes[-1]
                               if result.standard_error_notes else ""))
            self.params.show_current(result.parameters)
            self.view.show_gains(result.gains, f"{label} iteration {result.iteration}")
            self._update_images()
            self._update_actions()

        def failed(exc: BaseException) -> None:
            if isinstance(exc, grpc.RpcError) and exc.code() == \
                    grpc.StatusCode.FAILED_PRECONDITION and self.job is not None \
                    and self.job.name == name:
                self.result = None
                self.view.result_label.setText("no results: " + _details(exc))
                self._update_images()
                self._update_actions()

        self._call(f"{'estimating the standard errors' if estimate else 'fetching the result'}"
                   f" of {name}",
                   lambda c: c.jobs.GetJobResult(pb.GetJobResultRequest(
                       name=name, which=pb.WHICH_LAST if which == "last" else pb.WHICH_BEST,
                       estimate_standard_errors=estimate),
                       timeout=ESTIMATE_TIMEOUT_S if estimate else CALL_TIMEOUT_S),
                   # a refused estimate (the job resumed meanwhile) is a banner, and the
                   # result shown stays
                   done, None if estimate else failed,
                   quiet_codes=() if estimate else (grpc.StatusCode.FAILED_PRECONDITION,))

    def use_result_as_start(self) -> None:
        """The shown result becomes the next job's start: its values go into the table
        (scalars and colours, to see and edit), and the job is created with
        ``initial_from_job`` so that parameters too large for the table (textures, vertex
        arrays) continue from the result as well, without uploading anything."""
        if self.result is None or self.job is None:
            return
        count = 0
        for value in self.result.parameters:
            if value.value and value.key in self.params.keys():
                self.params.set_initial(value.key, value.value)
                count += 1
        self.setup.set_initial_from((self.job.name, self.result.which or pb.WHICH_BEST))
        self.status(f"{count} start value(s) taken from {self.job.name} "
                    f"(iteration {self.result.iteration}); edit and Start")

    def export_dialog(self) -> None:
        if self.job is None:
            return
        directory = QFileDialog.getExistingDirectory(
            self, f"Export {self.job.name} ({self.view.which()}) to", self.store.folder("export"))
        if directory:
            self.store.set_folder("export", directory)
            self.export_to(directory)

    def export_to(self, directory: str | os.PathLike) -> None:
        """Writes the same files as ``matopt job export`` (parameters.json, images,
        history.csv) for the best or last iteration, whichever is shown."""
        if self.job is None:
            return
        name, which, folder = self.job.name, self.view.which(), os.fspath(directory)
        self.status(f"exporting {name} to {folder}…")

        def done(export) -> None:
            self.status(f"exported {len(export.files)} files of {name} ({which} iteration "
                        f"{export.result.iteration}) to {folder}", 15000)
            self.show_banner(f"exported {name} ({which}) to {folder}", "info")

        self._call(f"exporting {name}", lambda c: export_job(c, name, folder, which), done)

    def _update_images(self) -> None:
        """Reference beside render for the chosen sensor: the result's images when there are
        results, else the reference file and the latest preview."""
        sensor = self.view.sensor_index()
        ref_pane, render_pane = self.view.reference, self.view.render
        if sensor is None:
            ref_pane.set_placeholder("no scene")
            render_pane.set_placeholder("no scene")
            return
        images = {(i.sensor, i.role): i for i in (self.result.images if self.result else [])}

        reference = images.get((sensor, "reference"))
        if reference is not None:
            self._show_blob(ref_pane, reference.png_blob, f"sensor {sensor}, as the job saw it")
        else:
            self._show_reference_file(sensor)

        role = self.view.role.currentText()
        rendered = images.get((sensor, role))
        if rendered is not None:
            label = "best" if self.result.which != pb.WHICH_LAST else "last"
            iteration = f"{label} iteration {self.result.iteration}"
            caption = {"initial": "initial values",
                       "error": f"|optimized − reference|, {iteration}"}.get(
                           role, f"{role}, {iteration}")
            self._show_blob(render_pane, rendered.png_blob, caption)
        elif self.result is not None:
            render_pane.set_placeholder(f"no {role} image of sensor {sensor} in the result")
        elif sensor in self.previews:
            image, caption = self.previews[sensor]
            self._wanted[id(render_pane)] = None
            render_pane.set_image(image, caption)
        else:
            render_pane.set_placeholder("no render yet" if self.job is None or self.job.state
                                        in mc.TERMINAL_STATES else
                                        "waiting for the first preview…")

    def _show_reference_file(self, sensor: int) -> None:
        pane = self.view.reference
        ref = self.references.reference(sensor)
        if ref is None:
            self._wanted[id(pane)] = None
            pane.set_placeholder(f"no reference image for sensor {sensor}")
            return
        key = ref.image
        if pane.key == key:
            return
        exr_note = (f"{ref.filename}: OpenEXR, shown once the job has results"
                    if ref.filename.lower().endswith(".exr") else "cannot display this image")
        self._wanted[id(pane)] = key
        if not ref.on_server:
            path = ref.image
            self.tasks.submit(lambda: read_image(path),
                              lambda image: self._deliver(pane, key, image, ref.filename,
                                                          exr_note),
                              what=f"reading {ref.filename}")
        else:
            blob = ref.image
            self._call("fetching the reference image",
                       lambda c: self.cache.image(c, blob),
                       lambda image: self._deliver(pane, key, image, ref.filename, exr_note))

    def _show_blob(self, pane, blob: str, caption: str) -> None:
        if pane.key == blob:
            pane.caption.setText(caption)
            return
        self._wanted[id(pane)] = blob
        self._call("fetching an image", lambda c: self.cache.image(c, blob),
                   lambda image: self._deliver(pane, blob, image, caption))

    def _deliver(self, pane, key: str, image, caption: str,
                 placeholder: str = "cannot display this image") -> None:
        if self._wanted.get(id(pane)) == key:  # not superseded by another sensor or result
            pane.set_image(image, caption, key=key, placeholder=placeholder)

    def _preview_tick(self) -> None:
        """While the job runs: render the latest iterate for the chosen sensor at low spp.

        RenderScene takes its turn on the daemon's device between iterations, so it slows the
        job down; a render that took longer than a fifth of the interval stretches the
        interval, keeping the cost to about 20% at most.
        """
        job, record, sensor = self.job, self.latest, self.view.sensor_index()
        if (self._preview_busy or job is None or job.state != pb.JOB_STATE_RUNNING or record is None
                or sensor is None or not self.view.live.isChecked()
                or not self.connection.usable or self.result is not None):
            return
        sent = {p.key for p in record.parameters}
        missing = [p.key for p in job.spec.parameters if p.key not in sent]
        if missing:
            self.view.render.set_placeholder(
                "no live preview: large parameters (" + ", ".join(missing[:3]) + ") are not "
                "sent per iteration; the render appears with the results")
            return
        values = [pb.ParameterValue(key=p.key, value=p.value, shape=p.shape)
                  for p in record.parameters]
        spp, iteration, started = self.preview_spp, record.iteration, time.monotonic()

        def render(c: mc.Client):
            response = c.scenes.RenderScene(pb.RenderSceneRequest(
                name=job.spec.scene, parameters=values, spp=spp, sensors=[sensor]),
                timeout=CALL_TIMEOUT_S * 4)
            return self.cache.image(c, response.images[0].png_blob), time.monotonic() - started

        def done(rendered) -> None:
            self._preview_busy = False
            image, seconds = rendered
            base = int(self.preview_interval_s * 1000)
            self.preview_timer.setInterval(max(base, int(seconds * 5000)))
            if self.job is None or self.job.name != job.name:
                return
            self.previews[sensor] = (image, f"preview of iteration {iteration} ({spp} spp, "
                                            f"{seconds:.2f} s)")
            self._update_images()

        def failed(exc: BaseException) -> None:
            self._preview_busy = False

        self._preview_busy = True
        self._call("rendering a preview", render, done, failed)


def _details(exc: grpc.RpcError) -> str:
    return " ".join((exc.details() or "").split())

"""The window's job: building the spec from the setup and starting it, opening a job from
the list, following it (history, then the live stream), and pause/resume/cancel.

A part of :class:`matopt_client.qt.app.MainWindow`, kept in a module of its own: its methods use the
window's panels and its ``_call`` (a daemon call off the GUI thread).
"""

from __future__ import annotations

import grpc
from PySide6.QtCore import Qt, Slot

from matopt_client import client as mc
from matopt_client import workflow
from matopt_client.qt.worker import CALL_TIMEOUT_S, JobWatcher
from matopt_api.v1 import matopt_pb2 as pb


def _fetch_job(client: mc.Client, name: str, known_scene: str | None
               ) -> tuple[pb.Job, pb.Scene | None, list[pb.Parameter] | None, str]:
    """Worker thread: the job, and its scene and parameters unless the window has them.

    A job whose scene was deleted can still be watched and exported; the last element
    explains why it cannot be restarted.
    """
    job = client.jobs.GetJob(pb.GetJobRequest(name=name), timeout=CALL_TIMEOUT_S)
    if job.spec.scene == known_scene:
        return job, None, None, ""
    try:
        scene = client.scenes.GetScene(pb.GetSceneRequest(name=job.spec.scene),
                                       timeout=CALL_TIMEOUT_S)
        parameters = client.scenes.ListSceneParameters(
            pb.ListSceneParametersRequest(name=scene.name), timeout=CALL_TIMEOUT_S).parameters
    except grpc.RpcError as exc:
        if exc.code() != grpc.StatusCode.NOT_FOUND:
            raise
        return job, None, None, (f"the job's scene {job.spec.scene} no longer exists: the "
                                 f"job can be watched and exported, not restarted")
    return job, scene, list(parameters), ""

class JobControl:
    """Starting, showing, following and controlling jobs (a part of MainWindow)."""

    def build_spec(self) -> pb.JobSpec:
        """The JobSpec of the setup, references not yet uploaded; ValueError says what is
        missing or malformed, as a sentence for the banner."""
        if self.scene is None:
            raise ValueError("open a scene first")
        parameters = self.params.specs()
        if not parameters:
            raise ValueError("select at least one parameter to optimize (tick its box in the "
                             "Optimize column)")
        if not self.references.references():
            raise ValueError(f"choose the reference images: one per sensor "
                             f"({len(self.scene.sensors)} for this scene)")
        base = self.setup.base_spec  # a restart keeps what the form has no field for
        if base is not None and base.scene != self.scene.name:
            base = None
        return workflow.build_spec(self.scene.name, parameters, self.settings.values(),
                                   base=base)

    def start_job(self) -> None:
        """Creates a job from the setup: uploads the local reference images (not those
        already on the server, as after opening a job to restart it) and starts watching."""
        if self._starting:
            return
        try:
            spec = self.build_spec()
        except ValueError as exc:
            self.show_banner(f"cannot start: {exc}", "warning")
            return
        references = self.references.references()
        initial_from = self.setup.initial_from

        def create(c: mc.Client) -> pb.Job:
            # initial_from: large parameters continue from the result too
            return workflow.start_job(
                c, spec, references, initial_from,
                lambda f, n: self._upload_note.emit(f"uploading {f}…"), CALL_TIMEOUT_S * 2)

        def done(job: pb.Job) -> None:
            self._starting = False
            self._update_actions()
            if self.banner.level == "warning":
                self.banner.clear()
            self.status(f"started {job.name}")
            # The references are on the server now: a restart must not upload them again.
            self.references.set_from_spec(job.spec.references)
            # The table now shows what the job starts from (start values taken over from a
            # result included), so that a restart reproduces it plus the user's edits.
            self.params.apply_specs(job.spec.parameters)
            self.setup.set_initial_from(None)
            self.setup.set_base_spec(job.spec, job.name)
            self.show_job(job)
            self.refresh_jobs()

        def failed(exc: BaseException) -> None:
            self._starting = False
            self._update_actions()

        self._starting = True
        self._update_actions()
        self.status("starting the job…")
        self._call("starting the job", create, done, failed)

    restart_job = start_job  # the setup holds the opened job's spec with the user's edits

    def open_job(self, name: str) -> None:
        """Shows a job from the list (any client's) and loads its spec into the setup, so it
        can be edited and restarted without uploading anything again."""
        known = self.scene.name if self.scene else None

        def done(fetched) -> None:
            job, scene, parameters, problem = fetched
            if scene is not None:
                self._set_scene(scene, parameters or [])
            if problem:
                self.show_banner(problem, "warning")
            elif job.spec.scene == (self.scene.name if self.scene else None):
                unknown = self.params.apply_specs(job.spec.parameters)
                self.references.set_from_spec(job.spec.references)
                self.settings.apply(job.spec)
                self.setup.set_base_spec(job.spec, job.name)
                self.setup.set_initial_from(None)
                if unknown:
                    self.show_banner(f"parameters of {job.name} not in its scene any more: "
                                     f"{', '.join(unknown)}", "warning")
            self.show_job(job)

        self.status(f"opening {name}…")
        self._call(f"opening {name}", lambda c: _fetch_job(c, mc.resource_name("jobs", name),
                                                           known), done)

    def show_job(self, job: pb.Job | None) -> None:
        """Shows ``job`` on the right and follows it (history first, then the live stream)."""
        self._stop_watching()
        self.job, self.result, self.latest, self.best_loss = job, None, None, None
        self.previews = {k: v for k, v in self.previews.items() if job is None}
        self.view.plot.clear()
        self.view.result_label.setText("")
        self.view.show_truth_errors(None)
        self.view.show_gains([])
        self.params.clear_current()
        self.jobs.set_current(job.name if job else None)
        self.view.show_job(job)
        if job is None:
            self.view.plot.set_target(None)
            self._update_title()
            self._update_images()
            self._update_actions()
            return
        self.view.plot.set_target(job.spec.min_error if job.spec.HasField("min_error") else None)
        best = workflow.best(job)
        if best is not None:
            self.best_loss = best[1]
            self.view.plot.set_best_iteration(best[0])
        self._update_title()
        self._load_history(job.name)
        self._watch(job.name)
        if job.state in mc.TERMINAL_STATES:
            self._fetch_result()
        self._update_images()
        self._update_actions()

    def _reopen_job(self, name: str) -> None:
        """After a reconnect: the job's state, the iterations missed, and a new stream."""
        def done(job: pb.Job) -> None:
            if self.job is not None and self.job.name == job.name:
                self._job_changed(job)
                self._load_history(job.name)
                self._watch(job.name)
        self._call(f"fetching {name}",
                   lambda c: c.jobs.GetJob(pb.GetJobRequest(name=name), timeout=CALL_TIMEOUT_S),
                   done)

    def _load_history(self, name: str) -> None:
        def done(records: list[pb.IterationRecord]) -> None:
            if self.job is None or self.job.name != name:
                return
            self.view.plot.extend((r.iteration, r.seconds, r.loss, _errors(r)) for r in records)
            if records and (self.latest is None
                            or records[-1].iteration > self.latest.iteration):
                self._iteration(records[-1], plot=False)
        self._call(f"fetching the history of {name}",
                   lambda c: mc.job_history(c, name), done)  # every page

    def _watch(self, name: str) -> None:
        client = self.connection.client
        if client is None:
            return
        self._stop_watching()
        self._watch_generation += 1
        watcher = JobWatcher(client, name, self._watch_generation, self)
        queued = Qt.ConnectionType.QueuedConnection
        watcher.event.connect(self._watch_event, queued)
        watcher.failed.connect(self._watch_failed, queued)
        watcher.ended.connect(self._watch_ended, queued)
        self._watcher = watcher
        watcher.start()

    def _stop_watching(self) -> None:
        if self._watcher is not None:
            self._watcher.stop()
            self._old_watchers.append(self._watcher)
            self._watcher = None
        self._watch_generation += 1  # whatever the old one still queued is dropped

    @Slot(int, object)
    def _watch_event(self, generation: int, event: pb.JobEvent) -> None:
        if generation != self._watch_generation or self.job is None:
            return
        if event.HasField("job"):
            self._job_changed(event.job)
        else:
            self._iteration(event.iteration)

    @Slot(int, object)
    def _watch_failed(self, generation: int, exc: BaseException) -> None:
        if generation != self._watch_generation or self.job is None:
            return
        if not self.connection.report(exc):
            self.show_banner(f"following {self.job.name} failed: "
                             f"{self.connection.describe(exc)}")

    @Slot(int)
    def _watch_ended(self, generation: int) -> None:
        self._old_watchers = [w for w in self._old_watchers if w.isRunning()]
        if self._watcher is not None and self._watcher.generation == generation:
            self._old_watchers.append(self._watcher)
            self._watcher = None

    def _job_changed(self, job: pb.Job) -> None:
        previous = self.job
        if (previous is not None and previous.name == job.name
                and job.update_time.ToNanoseconds() < previous.update_time.ToNanoseconds()):
            # A Pause/Resume reply that the watch stream overtook (the worker acted on the
            # request before the reply reached this thread): showing it would undo the newer
            # state, and no later state event would come to correct it.
            return
        self.job = job
        self.jobs.update_job(job)
        self.view.show_job(job)
        best = workflow.best(job)  # the daemon's, sent after each batch of iterations
        if best is not None:
            self.best_loss = best[1]
            self.view.plot.set_best_iteration(best[0])
        self._update_title()
        self._update_actions()
        changed = previous is None or previous.state != job.state
        if not changed:
            return
        if job.state in mc.TERMINAL_STATES:
            self._load_history(job.name)  # the complete curve, whatever the stream missed
            self._fetch_result()
            if job.state == pb.JOB_STATE_FAILED:
                self.show_banner(f"{job.name} FAILED: {job.error or 'no reason given'}")
            else:
                self.status(f"{job.name} {workflow.state_text(job)}")
        elif job.state == pb.JOB_STATE_INTERRUPTED:
            # The daemon stopped while the job ran: is it still there at all?
            self.connection.check_now()
            self.status(f"{job.name} was interrupted: Resume continues it from its last "
                        f"checkpoint")

    def _iteration(self, record: pb.IterationRecord, plot: bool = True) -> None:
        if plot:
            self.view.plot.add(record.iteration, record.seconds, record.loss, _errors(record))
        if self.latest is not None and record.iteration < self.latest.iteration:
            return
        self.latest = record
        done = record.iteration + 1  # records count from 0
        self.view.progress.setValue(min(done, self.view.progress.maximum()))
        self.view.set_numbers(done, record.loss, self.best_loss, record.seconds)
        self.view.show_truth_errors(record)
        if self.result is None:  # else the table and the gains are the result's
            self.params.show_current(record.parameters)
            self.view.show_gains(record.gains, f"iteration {record.iteration}")

    def _update_title(self) -> None:
        parts = ["matopt"]
        if self.scene:
            parts.append(self.scene.display_name)
        if self.job:
            parts.append(f"{self.job.name.rsplit('/', 1)[-1]} ({mc.state_name(self.job.state)})")
        self.setWindowTitle(" — ".join(parts))

    def pause_job(self) -> None:
        self._control("PauseJob", pb.PauseJobRequest, "pausing")

    def resume_job(self) -> None:
        self._control("ResumeJob", pb.ResumeJobRequest, "resuming")

    def cancel_job(self) -> None:
        self._control("CancelJob", pb.CancelJobRequest, "cancelling")

    def _control(self, rpc: str, request_type, verb: str) -> None:
        """Pause/resume/cancel act at the next iteration boundary; the stream shows when."""
        if self.job is None:
            return
        name = self.job.name

        def done(job: pb.Job) -> None:
            if self.job is None or self.job.name != name:
                return
            self._job_changed(job)
            self.status(f"{verb} {name}: takes effect at the next iteration")
            if self._watcher is None and job.state not in mc.TERMINAL_STATES:
                self._watch(name)  # e.g. resuming an INTERRUPTED job whose stream had ended

        self._call(f"{verb} {name}", lambda c: getattr(c.jobs, rpc)(
            request_type(name=name), timeout=CALL_TIMEOUT_S), done)


def _errors(record: pb.IterationRecord) -> dict[str, float]:
    """Each parameter's relative error against the job's ground truth (none without it)."""
    return {e.key: e.relative for e in record.errors}

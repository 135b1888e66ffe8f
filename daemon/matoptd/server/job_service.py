"""JobService: a job admitted here (its spec checked and defaulted once, its cost estimated,
its references read by a worker), then run by the scheduling; status calls (GetJob, ListJobs,
WatchJob, history, results) are served from the store and the watchers' events, never from a
worker."""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import uuid

from google.protobuf import empty_pb2

from matopt_api import costs, enums
from matopt_api.v1 import matopt_pb2 as pb
from matopt_api.v1 import matopt_pb2_grpc as rpc

from ..engine_api import ParameterInfo
from ..errors import FailedPrecondition
from ..logs import about
from ..records import ACTIVE, JobRecord, Phase, SceneRecord
from ..store.outputs import results_from_history
from . import admission, convert, job_spec
from .backend import Backend
from .interceptors import caller
from .paging import next_token, page, resource
from .scene_service import films

log = logging.getLogger("matoptd.server")

HISTORY_PAGE, MAX_HISTORY_PAGE = 1000, 10000


def which(value: int) -> str:
    """"best" or "last" (UNSPECIFIED: best)."""
    return enums.short_name(pb.Which, value or pb.WHICH_BEST).lower()


class JobService(rpc.JobServiceServicer):
    def __init__(self, backend: Backend) -> None:
        self.backend = backend
        self.store, self.control = backend.store, backend.control
        self.converted = convert.Converted()

    async def CreateJob(self, request, context):
        user = caller()
        if request.request_id:
            existing = self.store.job_by_request(user, request.request_id)
            if existing:
                return convert.job_to_pb(existing)
        # Off the event loop: the checks decode .npy values and read image headers, which for
        # large values, beside CPU workers at the server's low priority, takes a while; other
        # users' calls (a cancel, a status) are answered meanwhile.
        scene, params, built, estimate = await asyncio.to_thread(self._checked, user, request)
        settings = built.settings
        with self.backend.tasks.hold(user):
            await self.backend.lanes.run_task(
                lambda engine: engine.check_references(settings.references))
        self._admit_another(user)  # again: other requests of this user may have come first
        job = JobRecord(name=f"jobs/{uuid.uuid4().hex[:12]}", owner=user, scene=scene.name,
                        settings=settings,
                        shapes={p.key: list(params[p.key].shape) for p in settings.parameters})
        job.notes.extend(built.notes)
        job.notes.extend(costs.parameter_cost(p.key, params[p.key].shape,
                                              estimate.samples_per_iteration)
                         for p in settings.parameters if costs.is_large(params[p.key].shape))
        created = self.control.create(job, request.request_id)
        log.info("%s of %s admitted: %s", job.name, user, estimate.summary,
                 extra=about(job.name, user))
        return convert.job_to_pb(created)

    def _checked(self, user: str, request: pb.CreateJobRequest
                 ) -> tuple[SceneRecord, dict[str, ParameterInfo], job_spec.Built,
                            admission.Estimate]:
        """The spec checked and defaulted, and the job's cost admitted: what needs no worker."""
        self._admit_another(user)
        scene = self.store.get_scene(user, resource("scenes", request.spec.scene))
        self.store.blobs.check_room(user)
        # Before any other check: another user's blob must fail exactly as a missing one.
        for sha in sorted(job_spec.given_blobs(request.spec)):
            self.store.blobs.file(sha, user)
        listing = self.store.scene_parameters(user, scene.name)
        params = {p.key: p for p in listing}
        start = self._start_from(user, request) if request.initial_from_job else None
        built = job_spec.build(request.spec, scene, params, self.store.blobs.reader(user),
                               start, self.backend.limits.max_samples)
        estimate = admission.admit_job(built.settings, films(scene), self.store.blobs.file,
                                       self.backend.limits)
        return scene, params, built, estimate

    def _admit_another(self, user: str) -> None:
        """Refuses a user's job beyond --max-jobs-per-user active ones."""
        admission.check_jobs(user, self.store.count_jobs(user, ACTIVE), self.backend.limits)

    def _start_from(self, user: str, request: pb.CreateJobRequest) -> job_spec.StartFrom:
        """A restart: parameters without an initial value of their own start where another
        job's result left them (values inline, large ones by blob: nothing is re-uploaded)."""
        source = resource("jobs", request.initial_from_job)
        self.store.get_job(source, user)
        chosen = which(request.initial_from_which)
        result = self.store.result(source, chosen)
        if result is None:
            raise FailedPrecondition(f"job '{source}' has no {chosen.upper()} result to start "
                                     "from")
        return job_spec.StartFrom(source, chosen, result)

    async def GetJob(self, request, context):
        return self.converted.job(self.store.get_job(resource("jobs", request.name), caller()))

    async def ListJobs(self, request, context):
        offset, limit = page(request.page_token, request.page_size)
        found = self.store.list_jobs(caller(), offset, limit, convert.phases(request.state))
        return pb.ListJobsResponse(jobs=[convert.job_to_pb(j) for j in found],
                                   next_page_token=next_token(offset, limit, len(found)))

    async def DeleteJob(self, request, context):
        self.control.delete(caller(), resource("jobs", request.name))
        return empty_pb2.Empty()

    async def PauseJob(self, request, context):
        return convert.job_to_pb(self.control.pause(caller(), resource("jobs", request.name)))

    async def ResumeJob(self, request, context):
        user, name = caller(), resource("jobs", request.name)
        if self.store.get_job(name, user).phase in (Phase.PAUSED, Phase.INTERRUPTED):
            self._admit_another(user)  # it queues again
        return convert.job_to_pb(self.control.resume(user, name))

    async def CancelJob(self, request, context):
        return convert.job_to_pb(self.control.cancel(caller(), resource("jobs", request.name)))

    async def WatchJob(self, request, context):
        user, name = caller(), resource("jobs", request.name)
        self.store.get_job(name, user)  # NOT_FOUND before subscribing
        events = self.backend.events
        queue = events.subscribe(name)
        try:
            job = self.store.get_job(name, user)
            yield pb.JobEvent(job=self.converted.job(job))
            if job.phase.final:
                return
            while True:
                event = await queue.get()
                if isinstance(event, JobRecord):
                    job = event
                yield self.converted.event(event, job)
                if event is job and job.phase.final:
                    return
        finally:
            events.unsubscribe(name, queue)

    async def GetJobResult(self, request, context):
        name = resource("jobs", request.name)
        job = self.store.get_job(name, caller())
        chosen = which(request.which)
        result = self.store.result(name, chosen)
        if result is None and not job.phase.final:  # what its iterations so far reported
            result = next((r for r in results_from_history(job, self.store.history(name))
                           if r.which == chosen), None)
        if result is None:
            raise FailedPrecondition(f"job '{name}' has no {chosen.upper()} result "
                                     f"({job.phase.state}): results exist once a job "
                                     "has finished its first iteration")
        if not request.estimate_standard_errors or job.phase.final:
            return convert.result_to_pb(result, job)
        if job.phase is not Phase.PAUSED:
            raise FailedPrecondition(
                f"job '{name}' is {job.phase.state}: standard errors are estimated on request "
                "for a paused job (pause it first); an ended job's results carry them")
        checkpoint = self.store.checkpoints.read(name)
        if checkpoint is None:
            raise FailedPrecondition(f"job '{name}' was paused before its first checkpoint: "
                                     "resume it for a few iterations, then pause it again")
        settings = job.settings
        # In pieces of a step's time on one worker, other jobs' turns between them: an
        # estimate may take a minute.
        run, seconds = f"{name}#estimate-{uuid.uuid4().hex[:8]}", self.backend.lanes.step_seconds
        loaded = False

        def piece(engine):
            # The checkpoint (megabytes with textures) goes with the first piece only, and
            # again should a piece find the run gone (its worker restarted).
            nonlocal loaded
            if loaded:
                try:
                    return engine.estimate(run, None, None, chosen, seconds)
                except FailedPrecondition:
                    pass
            loaded = True
            return engine.estimate(run, settings, checkpoint, chosen, seconds)

        with self.backend.tasks.hold(caller()):
            estimated = await self.backend.lanes.run_in_pieces(
                piece, lambda engine: engine.release(run))
        result = dataclasses.replace(result, standard_errors=estimated.errors,
                                     gain_errors=estimated.gain_errors)
        out = convert.result_to_pb(result, job)
        out.standard_error_notes.extend(estimated.notes)
        return out

    async def GetJobHistory(self, request, context):
        name = resource("jobs", request.name)
        job = self.store.get_job(name, caller())
        offset, limit = page(request.page_token, request.page_size, HISTORY_PAGE,
                             MAX_HISTORY_PAGE)
        found = self.store.history(name, offset, limit)
        return pb.GetJobHistoryResponse(iterations=[convert.iteration_to_pb(r, job)
                                                    for r in found],
                                        next_page_token=next_token(offset, limit, len(found)))

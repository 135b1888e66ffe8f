"""The gRPC handlers: requests are checked here, in the caller's terms, before any engine work
is queued; engine work goes to a worker process through the runner. This process never
imports Mitsuba or Dr.Jit.

Every failure a user can cause becomes a canonical status code with a message naming the file,
key or value; anything else is INTERNAL, logged, and confined to that one request.
"""

from __future__ import annotations

import asyncio
import base64
import difflib
import functools
import logging
import math
import uuid

import grpc
from google.protobuf import empty_pb2
from google.protobuf.message import Message

from matoptd import __version__
from matopt_api import costs, enums
from matopt_api.v1 import matopt_pb2 as pb
from matopt_api.v1 import matopt_pb2_grpc as rpc

from . import admission, blob_refs, convert, engine_api as api, fields, range_notes, scenes
from .auth import Authenticator
from .errors import FailedPrecondition, InvalidArgument, UserError
from .runner import FINAL, Runner, now
from .store import CHUNK, Store

log = logging.getLogger("matoptd.server")

DEFAULT_ITERATIONS = 100
DEFAULT_MIN_ERROR = 0.0  # off: a fixed threshold ends dim scenes before they converge
DEFAULT_SPP = 16  # see parameters.DEFAULT_LEARNING_RATE: the same measurement
DEFAULT_PAGE, MAX_PAGE = 50, 1000
HISTORY_PAGE, MAX_HISTORY_PAGE = 1000, 10000


async def _guard(context, fn):
    """Runs a handler body, turning our exceptions into statuses."""
    try:
        return await fn()
    except UserError as exc:
        await context.abort(exc.code, str(exc))
    except (grpc.aio.AbortError, asyncio.CancelledError):
        raise
    except Exception as exc:  # noqa: BLE001 - one bad request must not take others down
        log.exception("internal error")
        await context.abort(grpc.StatusCode.INTERNAL, f"internal error: {type(exc).__name__}: "
                                                      f"{exc}")


async def _user(self, context) -> str:
    user = self.auth.user(context)
    if user is None:
        await context.abort(grpc.StatusCode.UNAUTHENTICATED,
                            "missing or unknown token: send 'authorization: Bearer <token>'")
    return user


async def _check_fields(request) -> None:
    if isinstance(request, Message):  # not the chunk stream of UploadBlob
        fields.check(request)


def unary(fn):
    """An RPC with one response, called as fn(self, request, context, user)."""
    @functools.wraps(fn)
    async def wrapper(self, request, context):
        user = await _user(self, context)
        await _guard(context, lambda: _check_fields(request))
        return await _guard(context, lambda: fn(self, request, context, user))
    return wrapper


def streaming(fn):
    """An RPC with a response stream, fn an async generator."""
    @functools.wraps(fn)
    async def wrapper(self, request, context):
        user = await _user(self, context)
        await _guard(context, lambda: _check_fields(request))
        gen = fn(self, request, context, user)
        while True:
            item = await _guard(context, lambda: _anext(gen))
            if item is _END:
                return
            yield item
    return wrapper


_END = object()


async def _anext(gen):
    try:
        return await gen.__anext__()
    except StopAsyncIteration:
        return _END


def _page(token: str, size: int, default: int = DEFAULT_PAGE,
          most: int = MAX_PAGE) -> tuple[int, int]:
    """(offset, limit) of a page. Tokens are opaque to clients (an offset in base64 behind a
    tag), so that the daemon may change what they hold without breaking anyone."""
    if size < 0:
        raise InvalidArgument(f"page_size must be >= 0, got {size}")
    offset = 0
    if token:
        try:
            tag, _, digits = base64.urlsafe_b64decode(token.encode("ascii")).decode().partition(":")
            offset = int(digits) if tag == "o" and digits.isdigit() and len(digits) <= 18 else -1
        except (ValueError, UnicodeError):
            offset = -1
        if offset < 0:
            raise InvalidArgument(f"invalid page_token '{token}': pass the next_page_token of "
                                  "the previous page unchanged, or nothing for the first")
    return offset, min(size or default, most)


def _next_token(offset: int, limit: int, got: int) -> str:
    if got < limit:
        return ""
    return base64.urlsafe_b64encode(f"o:{offset + limit}".encode()).decode()


def _name(prefix: str, name: str) -> str:
    """Accepts 'jobs/abc' or 'abc'."""
    if not name:
        raise InvalidArgument(f"name is empty: expected '{prefix}/<id>'")
    return name if name.startswith(prefix + "/") else f"{prefix}/{name}"


def _films(scene: pb.Scene) -> dict[int, tuple[int, int]]:
    return {s.index: (s.width, s.height) for s in scene.sensors}


class Service:
    """State shared by the servicers."""

    def __init__(self, store: Store, runner: Runner, auth: Authenticator,
                 limits: admission.Limits = admission.Limits()) -> None:
        self.store, self.runner, self.auth = store, runner, auth
        self.limits, self.tasks = limits, admission.TaskSlots(limits)


# -- blobs -----------------------------------------------------------------------------------

class BlobService(rpc.BlobServiceServicer):
    def __init__(self, svc: Service) -> None:
        self.store, self.auth = svc.store, svc.auth

    @unary
    async def FindMissingBlobs(self, request, context, user):
        return pb.FindMissingBlobsResponse(
            missing_sha256=[s for s in request.sha256 if not self.store.owns(user, s)])

    @unary
    async def UploadBlob(self, request_iterator, context, user):
        upload = self.store.begin_upload(user)
        try:
            header = None
            async for msg in request_iterator:
                if msg.HasField("header"):
                    if header is not None:
                        raise InvalidArgument("UploadBlob got a second header")
                    header = msg.header
                    self.store.blob_path(header.sha256)  # validates the digest's form
                    # Refused before the content travels; checked again when it is kept.
                    self.store.check_room(user, header.size_bytes, header.sha256)
                elif header is None:
                    raise InvalidArgument("UploadBlob must start with a header "
                                          "(sha256, size_bytes)")
                else:
                    upload.write(msg.chunk)
            if header is None:
                raise InvalidArgument("UploadBlob got no header")
            return upload.commit(header.sha256, header.size_bytes, within_quota=True)
        finally:
            upload.abort()

    @streaming
    async def DownloadBlob(self, request, context, user):
        path = self.store.blob_file(request.name, user)
        with open(path, "rb") as f:
            while chunk := f.read(CHUNK):
                yield pb.DownloadBlobResponse(chunk=chunk)

    @unary
    async def ListBlobs(self, request, context, user):
        offset, limit = _page(request.page_token, request.page_size)
        found = self.store.list_blobs(user, offset, limit)
        return pb.ListBlobsResponse(blobs=found,
                                    next_page_token=_next_token(offset, limit, len(found)),
                                    used_bytes=self.store.usage(user),
                                    quota_bytes=self.store.quota or 0)

    @unary
    async def DeleteBlob(self, request, context, user):
        self.store.delete_blob(user, _name("blobs", request.name))
        return empty_pb2.Empty()


# -- scenes ----------------------------------------------------------------------------------

class SceneService(rpc.SceneServiceServicer):
    def __init__(self, svc: Service) -> None:
        self.store, self.runner, self.auth = svc.store, svc.runner, svc.auth
        self.limits, self.tasks = svc.limits, svc.tasks

    @unary
    async def CreateScene(self, request, context, user):
        if request.request_id:
            existing = self.store.scene_by_request(user, request.request_id)
            if existing:
                return existing
        self.store.check_room(user)
        overrides = dict(request.overrides)
        if not request.main_file and not request.files:
            main = scenes.CORNELL_NAME
            paths = {main: self.store.put_blob(scenes.CORNELL_BOX.read_bytes(), user)
                     .removeprefix("blobs/")}
            display = request.display_name or "cornell-box"
            prepared = scenes.prepare(self.store.read_blob(paths[main]), main, overrides)
        else:
            # Off the event loop: a bundle's meshes are read through, which takes a while for
            # large ones, and other requests go on meanwhile.
            main, paths, prepared = await asyncio.to_thread(
                scenes.check_bundle, self.store, request.main_file, list(request.files),
                overrides, user)
            display = request.display_name or main.rsplit("/", 1)[-1]
        loadable = scenes.loadable_path(main)
        rewritten = {path: self.store.put_blob(xml, user).removeprefix("blobs/")
                     for path, xml in {**prepared.includes, loadable: prepared.xml}.items()}
        inputs = convert.scene_input(loadable, {**paths, **rewritten}, prepared.overrides, main)
        with self.tasks.hold(user):
            described = await self.runner.task(lambda engine: engine.describe_scene(inputs))
        scene = pb.Scene(name=f"scenes/{uuid.uuid4().hex[:12]}", display_name=display,
                         main_file=main, files=request.files, overrides=prepared.overrides,
                         warnings=prepared.warnings,
                         sensors=convert.sensors_to_pb(described.sensors),
                         has_media=described.has_media,
                         parameter_count=len(described.parameters))
        scene.create_time.CopyFrom(now())
        self.store.add_scene(user, request.request_id, scene, pb.ListSceneParametersResponse(
            parameters=[convert.parameter_to_pb(p) for p in described.parameters]),
            convert.scene_input_to_json(inputs))
        return scene

    @unary
    async def GetScene(self, request, context, user):
        return self.store.get_scene(user, _name("scenes", request.name))

    @unary
    async def ListScenes(self, request, context, user):
        offset, limit = _page(request.page_token, request.page_size)
        found = self.store.list_scenes(user, offset, limit)
        return pb.ListScenesResponse(scenes=found,
                                     next_page_token=_next_token(offset, limit, len(found)))

    @unary
    async def DeleteScene(self, request, context, user):
        name = _name("scenes", request.name)
        self.store.get_scene(user, name)  # NOT_FOUND first
        using = [j.name for j in self.store.list_jobs(user, 0, 1 << 30)
                 if j.spec.scene == name and j.state not in FINAL]
        if using:
            raise FailedPrecondition(
                f"scene '{name}' is used by {len(using)} unfinished job(s) "
                f"({', '.join(using[:3])}{', ...' if len(using) > 3 else ''}): a paused or "
                "interrupted job reloads its scene to resume; cancel or delete them first")
        self.store.delete_scene(user, name)
        return empty_pb2.Empty()

    @unary
    async def ListSceneParameters(self, request, context, user):
        return self.store.scene_parameters(user, _name("scenes", request.name))

    @unary
    async def RenderScene(self, request, context, user):
        scene = self.store.get_scene(user, _name("scenes", request.name))
        self.store.check_room(user)
        if request.HasField("spp") and request.spp < 1:
            raise InvalidArgument(f"spp must be >= 1, got {request.spp}")
        inputs = self.runner.scene_input(scene)
        render = convert.render_request(request, self.store.reader(user))
        params = {p.key: p for p in self.store.scene_parameters(user, scene.name).parameters}
        for key, values in render.values.items():
            _check_value(key, values, params, scene)
        admission.admit_render(render, _films(scene), self.limits)
        with self.tasks.hold(user):
            images = await self.runner.task(lambda engine: engine.render(inputs, render))
        return pb.RenderSceneResponse(images=[convert.image_to_pb(i, self.store.writer(user))
                                              for i in images])


def _listed(key: str, params: dict[str, pb.Parameter], scene: pb.Scene) -> pb.Parameter:
    """The scene's parameter ``key``, or INVALID_ARGUMENT with the closest listed key."""
    if key not in params:
        close = difflib.get_close_matches(key, list(params), n=1)
        hint = f"; did you mean '{close[0]}'?" if close else ""
        raise InvalidArgument(f"unknown parameter key '{key}' in scene '{scene.display_name}' "
                              f"(ListSceneParameters lists the parameters that can be set: the "
                              f"differentiable ones){hint}")
    return params[key]


def _check_value(key: str, values, params: dict[str, pb.Parameter], scene: pb.Scene) -> None:
    """A value given for a listed parameter: one finite number per component. Integer buffers
    (a mesh's faces) are not listed: the renderer would take their values as indices."""
    info = _listed(key, params, scene)
    size = math.prod(info.shape) if info.shape else 1
    if len(values) != size:
        raise InvalidArgument(f"parameter '{key}': got {len(values)} component(s), expected "
                              f"{size} (shape {list(info.shape)})")
    if not all(math.isfinite(v) for v in values):
        raise InvalidArgument(f"parameter '{key}': value is not finite")


# -- jobs ------------------------------------------------------------------------------------

def _check_spec(spec: pb.JobSpec, scene: pb.Scene, params: dict[str, pb.Parameter],
                store: Store) -> pb.JobSpec:
    """Validates a job's settings against its scene and fills in every default."""
    out = pb.JobSpec()
    out.CopyFrom(spec)
    out.scene = scene.name
    if spec.HasField("iterations") and spec.iterations < 1:
        raise InvalidArgument(f"iterations must be >= 1, got {spec.iterations}")
    if spec.HasField("spp") and spec.spp < 1:
        raise InvalidArgument(f"spp must be >= 1, got {spec.spp}")
    if spec.HasField("min_error") and not math.isfinite(spec.min_error):
        raise InvalidArgument(f"min_error must be finite, got {spec.min_error}")
    for field in ("film_height", "image_error_every", "image_error_spp"):
        if getattr(spec, field) < 0:
            raise InvalidArgument(f"{field} must be >= 0, got {getattr(spec, field)}")
    out.iterations = spec.iterations if spec.HasField("iterations") else DEFAULT_ITERATIONS
    out.spp = spec.spp if spec.HasField("spp") else DEFAULT_SPP
    out.min_error = spec.min_error if spec.HasField("min_error") else DEFAULT_MIN_ERROR
    out.loss = spec.loss or pb.LOSS_MSE
    out.schedule = spec.schedule or pb.SCHEDULE_COSINE
    default_lr = spec.learning_rate if spec.HasField("learning_rate") else None
    if default_lr is not None and not (math.isfinite(default_lr) and default_lr > 0):
        raise InvalidArgument(f"learning_rate must be > 0, got {default_lr}")

    count = len(scene.sensors)
    refs = list(spec.references)
    if spec.fit_exposure and not refs:
        raise InvalidArgument("fit_exposure fits one gain per reference image, but the job "
                              "has no reference images")
    if not refs:
        raise InvalidArgument(f"no reference images: the scene has {count} sensor(s)")
    explicit = [r.HasField("sensor") for r in refs]
    if any(explicit) and not all(explicit):
        raise InvalidArgument("either every reference names its sensor or none does")
    if not any(explicit) and len(refs) != count:
        raise InvalidArgument(f"got {len(refs)} reference image(s) for a scene with {count} "
                              f"sensor(s): give one per sensor, in order, or name the sensor "
                              f"of each")
    seen = set()
    for i, r in enumerate(refs):
        label = r.filename or r.blob
        index = r.sensor if r.HasField("sensor") else i
        if not 0 <= index < count:
            raise InvalidArgument(f"reference '{label}' names sensor {index}, but the scene "
                                  f"has {count} sensor(s)")
        if index in seen:
            raise InvalidArgument(f"two reference images for sensor {index}")
        seen.add(index)
        store.blob_file(r.blob)
        if r.mask_blob:
            store.blob_file(r.mask_blob)
        elif r.mask_filename:
            raise InvalidArgument(f"reference '{label}' names mask file '{r.mask_filename}' "
                                  "but no mask_blob: upload the mask and give its blob")

    if not spec.parameters:
        raise InvalidArgument("no parameters selected: name at least one key "
                              "(ListSceneParameters shows them)")
    keys = set()
    for p in out.parameters:
        info = _listed(p.key, params, scene)
        if p.key in keys:
            raise InvalidArgument(f"parameter '{p.key}' is selected twice")
        keys.add(p.key)
        lr = p.learning_rate if p.HasField("learning_rate") else (
            default_lr or info.default_learning_rate)
        if not (math.isfinite(lr) and lr > 0):
            raise InvalidArgument(f"learning rate of '{p.key}' must be > 0, got {lr}")
        lo = p.min if p.HasField("min") else info.min
        hi = p.max if p.HasField("max") else info.max
        if not lo < hi:
            raise InvalidArgument(f"range of '{p.key}' is empty: min {lo} >= max {hi}")
        if lo < info.min or hi > info.max:
            raise InvalidArgument(f"range [{lo}, {hi}] of '{p.key}' leaves its legal range "
                                  f"[{info.min}, {info.max}]")
        size = math.prod(info.shape) if info.shape else 1
        if p.initial_value and len(p.initial_value) != size:
            raise InvalidArgument(f"initial value of '{p.key}' has {len(p.initial_value)} "
                                  f"component(s), expected {size}")
        if any(not math.isfinite(v) for v in p.initial_value):
            raise InvalidArgument(f"initial value of '{p.key}' is not finite")
        if p.initial_blob:
            store.blob_file(p.initial_blob)
        if not (math.isfinite(p.smoothness) and p.smoothness >= 0):
            raise InvalidArgument(f"smoothness of '{p.key}' must be >= 0, got {p.smoothness}")
        if p.smoothness and info.kind not in (pb.PARAMETER_KIND_TEXTURE,
                                              pb.PARAMETER_KIND_VOLUME_GRID):
            raise InvalidArgument(f"smoothness applies to textures and grids; '{p.key}' is of "
                                  f"kind {enums.short_name(pb.ParameterKind, info.kind).lower()}")
        p.learning_rate, p.min, p.max = lr, lo, hi
    _check_choices(spec.choices)
    for t in out.ground_truth:
        if t.key not in params:
            raise InvalidArgument(f"ground truth for unknown parameter key '{t.key}'")
        size = math.prod(params[t.key].shape) if params[t.key].shape else 1
        if t.blob:
            store.blob_file(t.blob)
        elif len(t.value) != size:
            raise InvalidArgument(f"ground truth of '{t.key}' has {len(t.value)} "
                                  f"component(s), expected {size}")
    return out


def _check_choices(choices) -> None:
    """JobSpec.choices: names the engine has (or "all"), values it accepts."""
    names = [*api.CHOICES, api.ALL_CHOICES]
    for name, value in choices.items():
        if name not in names:
            close = difflib.get_close_matches(name, names, n=1)
            raise InvalidArgument(f"unknown choice '{name}'"
                                  + (f" (did you mean '{close[0]}'?)" if close else "")
                                  + f"; the choices are {', '.join(names)}")
        if value not in api.CHOICE_VALUES:
            raise InvalidArgument(f"choice '{name}' cannot be '{value}': give "
                                  f"{' or '.join(api.CHOICE_VALUES)}")


def _check_blob_sizes(spec: pb.JobSpec, settings: api.JobSettings,
                      params: dict[str, pb.Parameter]) -> None:
    """Initial values and ground truth given as .npy blobs: as many components as their
    parameter has (inline ones were counted by ``_check_spec``)."""
    given = [(f"initial value of '{p.key}'", p.initial_blob, p.key, s.initial)
             for p, s in zip(spec.parameters, settings.parameters)]
    given += [(f"ground truth of '{t.key}'", t.blob, t.key, settings.truth.get(t.key))
              for t in spec.ground_truth]
    for what, blob, key, value in given:
        shape = list(params[key].shape)
        size = math.prod(shape) if shape else 1
        if blob and value is not None and value.size != size:
            raise InvalidArgument(f"{what} ({blob}) has {value.size} component(s), expected "
                                  f"{size} (shape {shape})")


def _clip_notes(settings: api.JobSettings, restarted: set[str],
                request: pb.CreateJobRequest) -> list[str]:
    """Start values outside the job's range, which the engine clips into it: said up front,
    since a restart with a narrower range would otherwise quietly start elsewhere."""
    which = enums.short_name(pb.Which, request.initial_from_which or pb.WHICH_BEST).lower()
    notes = []
    for p in settings.parameters:
        if p.initial is None:
            continue
        source = (f"the {which} result of {_name('jobs', request.initial_from_job)}"
                  if p.key in restarted else "the initial value")
        note = range_notes.clip_note(p.key, p.initial, p.lo, p.hi, source)
        if note:
            notes.append(note)
    return notes


class JobService(rpc.JobServiceServicer):
    def __init__(self, svc: Service) -> None:
        self.store, self.runner, self.auth = svc.store, svc.runner, svc.auth
        self.limits, self.tasks = svc.limits, svc.tasks

    @unary
    async def CreateJob(self, request, context, user):
        if request.request_id:
            existing = self.store.job_by_request(user, request.request_id)
            if existing:
                return existing
        self._admit_another(user)
        scene = self.store.get_scene(user, _name("scenes", request.spec.scene))
        self.store.check_room(user)
        # Before any other check: another user's blob must fail exactly as a missing one.
        for sha in sorted(blob_refs.spec_blobs(request.spec)):
            self.store.blob_file(sha, user)
        params = {p.key: p for p in self.store.scene_parameters(user, scene.name).parameters}
        spec = _check_spec(request.spec, scene, params, self.store)
        restarted = self._start_from(user, request, spec) if request.initial_from_job else set()
        # Decoding every value now refuses a malformed .npy here, not when the job loads.
        settings = convert.job_settings(spec, self.runner.scene_input(scene),
                                        self.store.reader(user))
        _check_blob_sizes(spec, settings, params)
        estimate = admission.admit_job(settings, _films(scene), self.store.blob_file,
                                       self.limits)
        with self.tasks.hold(user):
            await self.runner.task(lambda engine: engine.check_references(settings.references))
        self._admit_another(user)  # again: other requests of this user may have come first
        job = pb.Job(name=f"jobs/{uuid.uuid4().hex[:12]}", spec=spec, state=pb.JOB_STATE_QUEUED,
                     owner=user, best_iteration=-1)
        job.notes.extend(_clip_notes(settings, restarted, request))
        job.notes.extend(costs.parameter_cost(p.key, params[p.key].shape,
                                              estimate.samples_per_iteration)
                         for p in spec.parameters if costs.is_large(params[p.key].shape))
        job.create_time.CopyFrom(now())
        job.update_time.CopyFrom(job.create_time)
        self.store.add_job(job, request.request_id)
        self.runner.submit(job)
        log.info("%s of %s admitted: %s", job.name, user, estimate.summary)
        return job

    def _admit_another(self, user: str) -> None:
        """Refuses a user's job beyond --max-jobs-per-user queued or running ones."""
        active = self.store.list_jobs(user, 0, self.limits.max_jobs_per_user,
                                      (pb.JOB_STATE_QUEUED, pb.JOB_STATE_RUNNING))
        admission.check_jobs(user, len(active), self.limits)

    def _start_from(self, user: str, request: pb.CreateJobRequest, spec: pb.JobSpec
                    ) -> set[str]:
        """A restart: parameters without an initial value of their own start where another
        job's result left them (values inline, large ones by blob: nothing is re-uploaded).
        Returns the keys that start so."""
        source = _name("jobs", request.initial_from_job)
        self.store.get_job(source, user)
        which = request.initial_from_which or pb.WHICH_BEST
        result = self.store.result(source, which)
        if result is None:
            raise FailedPrecondition(f"job '{source}' has no {enums.short_name(pb.Which, which)} result to "
                                     "start from")
        found = {v.key: v for v in result.parameters}
        taken = set()
        for p in spec.parameters:
            if p.initial_value or p.initial_blob or p.key not in found:
                continue
            taken.add(p.key)
            if found[p.key].blob:
                p.initial_blob = found[p.key].blob
            else:
                p.initial_value[:] = found[p.key].value
        return taken

    @unary
    async def GetJob(self, request, context, user):
        return self.store.get_job(_name("jobs", request.name), user)

    @unary
    async def ListJobs(self, request, context, user):
        offset, limit = _page(request.page_token, request.page_size)
        states = (request.state,) if request.state else ()
        found = self.store.list_jobs(user, offset, limit, states)
        return pb.ListJobsResponse(jobs=found,
                                   next_page_token=_next_token(offset, limit, len(found)))

    @unary
    async def DeleteJob(self, request, context, user):
        self.runner.delete(user, _name("jobs", request.name))
        return empty_pb2.Empty()

    @unary
    async def PauseJob(self, request, context, user):
        return self.runner.pause(user, _name("jobs", request.name))

    @unary
    async def ResumeJob(self, request, context, user):
        name = _name("jobs", request.name)
        if self.store.get_job(name, user).state in (pb.JOB_STATE_PAUSED, pb.JOB_STATE_INTERRUPTED):
            self._admit_another(user)  # it queues again
        return self.runner.resume(user, name)

    @unary
    async def CancelJob(self, request, context, user):
        return self.runner.cancel(user, _name("jobs", request.name))

    @streaming
    async def WatchJob(self, request, context, user):
        name = _name("jobs", request.name)
        self.store.get_job(name, user)  # NOT_FOUND before subscribing
        queue = self.runner.subscribe(name)
        try:
            job = self.store.get_job(name, user)
            yield pb.JobEvent(job=job)
            if job.state in FINAL:
                return
            while True:
                event = await queue.get()
                yield event
                if event.HasField("job") and event.job.state in FINAL:
                    return
        finally:
            self.runner.unsubscribe(name, queue)

    @unary
    async def GetJobResult(self, request, context, user):
        name = _name("jobs", request.name)
        job = self.store.get_job(name, user)
        which = request.which or pb.WHICH_BEST
        result = self.store.result(name, which)
        if result is None:
            raise FailedPrecondition(f"job '{name}' has no {enums.short_name(pb.Which, which)} result "
                                     f"({enums.short_name(pb.JobState, job.state)}): results exist once a job "
                                     f"succeeded or was cancelled after its first iteration")
        return result

    @unary
    async def GetJobHistory(self, request, context, user):
        name = _name("jobs", request.name)
        self.store.get_job(name, user)
        offset, limit = _page(request.page_token, request.page_size, HISTORY_PAGE,
                              MAX_HISTORY_PAGE)
        found = self.store.history(name, offset, limit)
        return pb.GetJobHistoryResponse(iterations=found,
                                        next_page_token=_next_token(offset, limit, len(found)))


# -- server ----------------------------------------------------------------------------------

class ServerService(rpc.ServerServiceServicer):
    def __init__(self, svc: Service) -> None:
        self.runner, self.auth = svc.runner, svc.auth

    @unary
    async def GetServerInfo(self, request, context, user):
        workers = self.runner.worker_listing(user)
        first = next((w for w in workers if w.variant), pb.Worker())
        return pb.ServerInfo(
            version=__version__, variant=first.variant, device=first.device, user=user,
            workers=workers, losses=enums.short_names(pb.Loss), schedules=enums.short_names(pb.Schedule),
            sensor_modes=enums.short_names(pb.SensorMode),
            integrators=["prb", "prbvolpath", "prb_projective", "direct_projective"],
            capabilities=["chunked-upload", "content-addressed-blobs", "pause-resume",
                          "checkpoint-resume", "watch", "render", "multi-user", "restart",
                          "ground-truth-errors", "image-error", "optimized-scene-export",
                          "worker-processes"])


def add_services(server: grpc.aio.Server, svc: Service) -> list[str]:
    """Registers the matopt services; returns their full names (for health and reflection)."""
    rpc.add_BlobServiceServicer_to_server(BlobService(svc), server)
    rpc.add_SceneServiceServicer_to_server(SceneService(svc), server)
    rpc.add_JobServiceServicer_to_server(JobService(svc), server)
    rpc.add_ServerServiceServicer_to_server(ServerService(svc), server)
    return [pb.DESCRIPTOR.services_by_name[n].full_name
            for n in ("BlobService", "SceneService", "JobService", "ServerService")]

"""SceneService: a bundle checked and prepared here (``bundles``), then described by a worker
(sensors, parameters) and kept; renders with the scene's own integrator."""

from __future__ import annotations

import asyncio
import math
import time
import uuid

from google.protobuf import empty_pb2

from matopt_api.v1 import matopt_pb2 as pb
from matopt_api.v1 import matopt_pb2_grpc as rpc

from ..engine_api import ParameterInfo, RenderRequest
from ..errors import FailedPrecondition, InvalidArgument
from ..records import SceneRecord
from ..settings import SceneInput
from ..store.outputs import keep_image
from . import admission, bundles, convert
from .backend import Backend
from .interceptors import caller
from .job_spec import listed, loadable
from .paging import next_token, page, resource


def films(scene: SceneRecord) -> dict[int, tuple[int, int]]:
    return {s.index: (s.width, s.height) for s in scene.sensors}


class SceneService(rpc.SceneServiceServicer):
    def __init__(self, backend: Backend) -> None:
        self.backend = backend
        self.store, self.blobs = backend.store, backend.store.blobs

    async def CreateScene(self, request, context):
        user = caller()
        if request.request_id:
            existing = self.store.scene_by_request(user, request.request_id)
            if existing:
                return convert.scene_to_pb(existing)
        self.blobs.check_room(user)
        overrides = dict(request.overrides)
        if not request.main_file and not request.files:
            main = bundles.CORNELL_NAME
            paths = {main: self.blobs.put(bundles.CORNELL_BOX.read_bytes(), user)}
            display = request.display_name or "cornell-box"
            prepared = bundles.prepare(self.blobs.read(paths[main]), main, overrides)
        else:
            # Off the event loop: a bundle's meshes are read through, which takes a while for
            # large ones, and other requests go on meanwhile.
            main, paths, prepared = await asyncio.to_thread(
                bundles.check_bundle, self.blobs, request.main_file, list(request.files),
                overrides, user)
            display = request.display_name or main.rsplit("/", 1)[-1]
        path = bundles.loadable_path(main)
        rewritten = {p: self.blobs.put(xml, user)
                     for p, xml in {**prepared.includes, path: prepared.xml}.items()}
        inputs = SceneInput.of(path, {**paths, **rewritten}, prepared.overrides, main)
        with self.backend.tasks.hold(user):
            described = await self.backend.lanes.run_task(
                lambda engine: engine.describe_scene(inputs))
        scene = SceneRecord(
            name=f"scenes/{uuid.uuid4().hex[:12]}", owner=user, display_name=display,
            main_file=main, files=convert.bundle_files(request.files),
            overrides=prepared.overrides, warnings=prepared.warnings,
            sensors=described.sensors, has_media=described.has_media,
            parameter_count=len(described.parameters), inputs=inputs, created=time.time())
        self.store.add_scene(scene, described.parameters, request.request_id)
        return convert.scene_to_pb(scene)

    async def GetScene(self, request, context):
        return convert.scene_to_pb(self.store.get_scene(caller(), resource("scenes",
                                                                          request.name)))

    async def ListScenes(self, request, context):
        offset, limit = page(request.page_token, request.page_size)
        found = self.store.list_scenes(caller(), offset, limit)
        return pb.ListScenesResponse(scenes=[convert.scene_to_pb(s) for s in found],
                                     next_page_token=next_token(offset, limit, len(found)))

    async def DeleteScene(self, request, context):
        user, name = caller(), resource("scenes", request.name)
        self.store.get_scene(user, name)  # NOT_FOUND first
        using = [j.name for j in self.store.list_jobs(user)
                 if j.scene == name and not j.phase.final]
        if using:
            raise FailedPrecondition(
                f"scene '{name}' is used by {len(using)} unfinished job(s) "
                f"({', '.join(using[:3])}{', ...' if len(using) > 3 else ''}): a paused or "
                "interrupted job reloads its scene to resume; cancel or delete them first")
        self.store.delete_scene(user, name)
        return empty_pb2.Empty()

    async def ListSceneParameters(self, request, context):
        listing = self.store.scene_parameters(caller(), resource("scenes", request.name))
        return pb.ListSceneParametersResponse(
            parameters=[convert.parameter_to_pb(p) for p in listing])

    async def RenderScene(self, request, context):
        user = caller()
        # Off the event loop, as CreateJob's checks: given values may be large .npy blobs.
        inputs, render = await asyncio.to_thread(self._render_checked, user, request)
        with self.backend.tasks.hold(user):
            images = await self.backend.lanes.run_task(
                lambda engine: engine.render(inputs, render))
        put = self.blobs.writer(user)
        return pb.RenderSceneResponse(images=[convert.image_to_pb(keep_image(i, put))
                                              for i in images])

    def _render_checked(self, user: str, request: pb.RenderSceneRequest
                        ) -> tuple[SceneInput, RenderRequest]:
        """The render asked for, checked and admitted: what needs no worker."""
        scene = self.store.get_scene(user, resource("scenes", request.name))
        self.blobs.check_room(user)
        if request.HasField("spp") and request.spp < 1:
            raise InvalidArgument(f"spp must be >= 1, got {request.spp}")
        inputs = loadable(scene)
        render = convert.render_request(request, self.blobs.reader(user))
        params = {p.key: p for p in self.store.scene_parameters(user, scene.name)}
        for key, values in render.values.items():
            _check_value(key, values, params, scene)
        admission.admit_render(render, films(scene), self.backend.limits)
        return inputs, render


def _check_value(key: str, values, params: dict[str, ParameterInfo], scene: SceneRecord
                 ) -> None:
    """A value given for a listed parameter: one finite number per component. Integer buffers
    (a mesh's faces) are not listed: the renderer would take their values as indices."""
    info = listed(key, params, scene)
    size = math.prod(info.shape) if info.shape else 1
    if len(values) != size:
        raise InvalidArgument(f"parameter '{key}': got {len(values)} component(s), expected "
                              f"{size} (shape {list(info.shape)})")
    if not all(math.isfinite(v) for v in values):
        raise InvalidArgument(f"parameter '{key}': value is not finite")

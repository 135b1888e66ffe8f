"""The engine's entry points, in API terms: protobuf messages in, protobuf messages out.

The scheduler calls these on its worker thread only. Files arrive as paths, outgoing images
leave through ``put_blob(bytes) -> "blobs/{sha256}"``, so the engine knows nothing of the
store.
"""

from __future__ import annotations

import io
import time
from pathlib import Path
from typing import Callable

import mitsuba as mi
import numpy as np

from matopt.v1 import matopt_pb2 as pb

from ..errors import InvalidArgument
from . import images, parameters, scene as scenes, variant
from .optimize import Optimization, Setting

PutBlob = Callable[[bytes], str]
RESULT_SPP = 64  # renders in results are off the clock; enough samples to look at


def init(requested_variant: str | None, data_dir: Path) -> tuple[str, str]:
    variant.configure_environment(data_dir)
    return variant.select(requested_variant)


def load(loadable: Path, overrides: dict[str, str], display: str) -> mi.Scene:
    return scenes.load(loadable, overrides, display)


def inspect(scene: mi.Scene) -> tuple[list[pb.Sensor], bool, list[pb.Parameter]]:
    d = scenes.describe(scene)
    params = mi.traverse(scene)
    sensors = [pb.Sensor(index=i, id=sid, width=w, height=h)
               for i, (sid, w, h) in enumerate(d.sensors)]
    return sensors, d.has_media, [parameters.to_proto(info, params[info.key])
                                  for info in d.parameters]


def _image(put_blob: PutBlob, pixels: np.ndarray, sensor: int, role: str) -> pb.Image:
    exr, png = images.encode(pixels)
    return pb.Image(sensor=sensor, role=role, width=pixels.shape[1], height=pixels.shape[0],
                    exr_blob=put_blob(exr), png_blob=put_blob(png))


def _decode_values(values: list[pb.ParameterValue], read_blob: Callable[[str], bytes]
                   ) -> dict[str, np.ndarray]:
    out = {}
    for v in values:
        if v.blob:
            out[v.key] = np.load(io.BytesIO(read_blob(v.blob))).ravel()
        else:
            out[v.key] = np.asarray(v.value, dtype=np.float32)
    return out


def render(scene: mi.Scene, request: pb.RenderSceneRequest, put_blob: PutBlob,
           read_blob: Callable[[str], bytes]) -> list[pb.Image]:
    """Renders with the scene's own integrator, parameters overridden, then restored."""
    count = len(scene.sensors())
    sensors = list(request.sensors) or list(range(count))
    for s in sensors:
        if not 0 <= s < count:
            raise InvalidArgument(f"sensor {s} does not exist: the scene has {count} sensor(s)")
    params = mi.traverse(scene)
    overrides = _decode_values(list(request.parameters), read_blob)
    saved = {}
    try:
        for key, v in overrides.items():
            if key not in params:
                raise InvalidArgument(f"unknown parameter key '{key}'")
            saved[key] = parameters.flat(params[key])
            try:
                params[key] = parameters.assign(params[key], v)
            except ValueError as exc:
                raise InvalidArgument(f"parameter '{key}': {exc}") from None
        params.update()
        # A scene without <integrator> renders with Mitsuba's default, the path tracer.
        integrator = scene.integrator() or mi.load_dict({"type": "path"})
        out = []
        for s in sensors:
            img = mi.render(scene, sensor=s, integrator=integrator, seed=request.seed,
                            spp=request.spp if request.HasField("spp") else 64)
            out.append(_image(put_blob, np.array(img, dtype=np.float32), s, "render"))
        return out
    finally:
        for key, v in saved.items():
            params[key] = parameters.assign(params[key], v)
        params.update()


def check_reference(path: Path, name: str, size: tuple[int, int]) -> None:
    images.read_reference(str(path), name, size)


def start_job(scene: mi.Scene, spec: pb.JobSpec, reference_paths: dict[int, tuple[Path, str]],
              read_blob: Callable[[str], bytes], checkpoint: bytes | None) -> Optimization:
    """Builds the optimization of a job (spec already validated and defaulted)."""
    began = time.perf_counter()
    sensors = scene.sensors()
    refs = {}
    for index, (path, name) in reference_paths.items():
        size = sensors[index].film().crop_size()
        refs[index] = images.read_reference(str(path), name, (int(size[0]), int(size[1])))
    settings = []
    for p in spec.parameters:
        initial = np.asarray(p.initial_value, dtype=np.float32) if p.initial_value else None
        settings.append(Setting(p.key, p.learning_rate, p.min, p.max, initial))
    opt = Optimization(scene, settings, refs, loss=spec.loss, iterations=spec.iterations,
                       min_error=spec.min_error, spp=spec.spp, seed=spec.seed,
                       cosine=spec.schedule != pb.CONSTANT)
    if checkpoint is not None:
        opt.restore(checkpoint)
    else:
        opt.elapsed += time.perf_counter() - began
    return opt


def values_to_proto(values: dict[str, np.ndarray], shapes: dict[str, list[int]],
                    put_blob: PutBlob | None) -> list[pb.ParameterValue]:
    """Small values inline; large ones as .npy blobs (or left out when put_blob is None)."""
    out = []
    for key, v in values.items():
        if v.size <= parameters.SMALL:
            out.append(pb.ParameterValue(key=key, value=v.tolist(), shape=shapes[key]))
        elif put_blob is not None:
            buf = io.BytesIO()
            np.save(buf, v.reshape(shapes[key]) if shapes[key] else v)
            out.append(pb.ParameterValue(key=key, shape=shapes[key], blob=put_blob(buf.getvalue())))
    return out


def results(opt: Optimization, job: str,
            chosen: list[tuple[int, int, float, dict[str, np.ndarray]]],
            shapes: dict[str, list[int]], put_blob: PutBlob) -> list[pb.JobResult]:
    """For each chosen (which, iteration, loss, values): the parameters and the renders
    (initial, optimized, reference per sensor). Initial and reference images are shared."""
    spp = max(RESULT_SPP, opt.spp)
    shared = {}
    for sensor, ref in opt.references.items():
        shared[sensor] = (_image(put_blob, opt.render(opt.initial, sensor, spp), sensor,
                                 "initial"),
                          _image(put_blob, np.array(ref, dtype=np.float32), sensor,
                                 "reference"))
    initial = values_to_proto(opt.initial, shapes, put_blob)
    out = []
    for which, iteration, loss, values in chosen:
        res = pb.JobResult(job=job, which=which, iteration=iteration, loss=loss,
                           parameters=values_to_proto(values, shapes, put_blob),
                           initial_parameters=initial)
        for sensor, (first, ref) in shared.items():
            optimized = _image(put_blob, opt.render(values, sensor, spp), sensor, "optimized")
            res.images.extend([first, optimized, ref])
        out.append(res)
    return out

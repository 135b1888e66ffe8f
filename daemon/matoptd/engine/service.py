"""The engine's entry points, in API terms: protobuf messages in, protobuf messages out.

The scheduler calls these on its worker thread only. Files arrive as paths, outgoing images
leave through ``put_blob(bytes) -> "blobs/{sha256}"``, so the engine knows nothing of the
store.
"""

from __future__ import annotations

import io
import posixpath
import time
from pathlib import Path
from typing import Callable

import mitsuba as mi
import numpy as np

from matopt_api.v1 import matopt_pb2 as pb

from ..errors import InvalidArgument
from . import diagnosis, images, parameters, scene as scenes, scene_export, variant
from .optimize import Config, Optimization, Reference, Setting

PutBlob = Callable[[bytes], str]
RESULT_SPP = 64  # renders in results are off the clock; enough samples to look at


def init(requested_variant: str | None, data_dir: Path) -> tuple[str, str]:
    variant.configure_environment(data_dir)
    return variant.select(requested_variant)


def load(loadable: Path, overrides: dict[str, str], display: str,
         keys: list[str] | None = None) -> mi.Scene:
    return scenes.load(loadable, overrides, display, keys)


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
    return {v.key: _array(v, read_blob, v.blob, v.value) for v in values}


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
            if v is None:
                raise InvalidArgument(f"parameter '{key}' has neither values nor a blob")
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


def check_reference(path: Path, name: str) -> None:
    images.read_reference(str(path), name)


def _array(value: pb.ParameterValue | pb.ParameterSpec, read_blob: Callable[[str], bytes],
           blob: str, values) -> np.ndarray | None:
    if blob:
        return np.load(io.BytesIO(read_blob(blob))).astype(np.float32).ravel()
    return np.asarray(values, dtype=np.float32) if len(values) else None


def _film_key(params: mi.SceneParameters, sensor: mi.Sensor) -> str | None:
    key = f"{sensor.id()}.film.size"
    return key if key in params else None


def _references(scene: mi.Scene, spec: pb.JobSpec, paths: dict[int, tuple[Path, str]],
                notes: list[str]) -> dict[int, Reference]:
    """Reads each reference and sizes its sensor's film: height from ``spec.resolution`` (or
    the film's own), width from the reference's aspect ratio. Each sensor keeps its own size.
    NaN/Inf pixels are masked out of every loss and counted."""
    params = mi.traverse(scene)
    sensors = scene.sensors()
    refs = {}
    for index, (path, name) in paths.items():
        image = images.read_reference(str(path), name)
        film = sensors[index].film().crop_size()
        height = spec.resolution or int(film[1])
        width = max(1, round(height * image.shape[1] / image.shape[0]))
        if (width, height) != (int(film[0]), int(film[1])):
            key = _film_key(params, sensors[index])
            if key is None:
                raise InvalidArgument(f"sensor {index}'s film cannot be resized to "
                                      f"{width}x{height} for reference '{name}'")
            params[key] = mi.ScalarVector2u(width, height)
            params.update()
            notes.append(f"sensor {index} renders {width}x{height} (film was "
                         f"{int(film[0])}x{int(film[1])}) to follow reference '{name}'")
        image = images.fit(image, (width, height))
        valid = np.isfinite(image).all(axis=2, keepdims=True)
        if not valid.all():
            notes.append(f"reference '{name}': {int((~valid).sum())} NaN/Inf pixel(s) masked "
                         "out of the loss")
        weight = np.broadcast_to(valid, image.shape).astype(np.float32)
        refs[index] = Reference(mi.TensorXf(np.where(weight > 0, image, 0.0)),
                                None if valid.all() else mi.TensorXf(weight))
    return refs


def start_job(scene: mi.Scene, spec: pb.JobSpec, reference_paths: dict[int, tuple[Path, str]],
              read_blob: Callable[[str], bytes], checkpoint: bytes | None) -> Optimization:
    """Builds the optimization of a job (spec already validated and defaulted)."""
    began = time.perf_counter()
    notes: list[str] = []
    refs = _references(scene, spec, reference_paths, notes)
    settings = [Setting(p.key, p.learning_rate, p.min, p.max,
                        _array(p, read_blob, p.initial_blob, p.initial_value))
                for p in spec.parameters]
    truth = {v.key: _array(v, read_blob, v.blob, v.value) for v in spec.ground_truth}
    config = Config(loss=spec.loss, iterations=spec.iterations, min_error=spec.min_error,
                    spp=spec.spp, seed=spec.seed, cosine=spec.schedule != pb.CONSTANT,
                    step_per_sensor=spec.sensor_mode == pb.STEP_PER_SENSOR, clamp=spec.clamp,
                    truth={k: v for k, v in truth.items() if v is not None},
                    image_error_every=spec.image_error_every,
                    image_error_spp=spec.image_error_spp or 64)
    opt = Optimization(scene, settings, refs, config)
    opt.notes = notes + [f"gradients for: {', '.join(opt.settings)}",
                         f"sensors rendered: {', '.join(map(str, opt.references))}"
                         + (f" (not rendered: {', '.join(map(str, skipped))})"
                            if (skipped := [i for i in range(len(scene.sensors()))
                                            if i not in opt.references]) else "")]
    if checkpoint is not None:
        opt.restore(checkpoint)
    else:
        opt.elapsed += time.perf_counter() - began
    return opt


def diagnose(opt: Optimization, values: dict[str, np.ndarray],
             history: list[pb.IterationRecord]) -> list[str]:
    opt.flush()
    paths: dict[str, list[list[float]]] = {}
    for record in history:
        for v in record.parameters:
            if v.value:
                paths.setdefault(v.key, []).append(list(v.value))
    return diagnosis.diagnose(opt.settings, values, [h.loss for h in history],
                              opt.nonfinite_steps, opt.skipped_steps,
                              {k: np.array(p) for k, p in paths.items() if len(p) == len(history)})


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


def _scene_bundle(opt: Optimization, scene: pb.Scene, loadable: Path,
                  values: dict[str, np.ndarray], shapes: dict[str, list[int]], put_blob: PutBlob,
                  res: pb.JobResult) -> None:
    """The optimized scene, next to the original main XML, with the bundle it needs."""
    with opt.holding(values) as held:
        files, unplaced = scene_export.optimized_scene(loadable, dict(scene.overrides), held,
                                                       values, shapes)
    base = posixpath.dirname(scene.main_file)
    new = {posixpath.join(base, path): put_blob(data) for path, data in files.items()}
    res.scene_files.extend(pb.BundleFile(path=f.path, sha256=f.sha256) for f in scene.files
                           if f.path not in new)
    res.scene_files.extend(pb.BundleFile(path=p, sha256=b.removeprefix("blobs/"))
                           for p, b in new.items())
    res.scene_file = posixpath.join(base, "scene_optimized.xml")
    res.unplaced_parameters.extend(unplaced)


def results(opt: Optimization, job: str,
            chosen: list[tuple[int, int, float, dict[str, np.ndarray]]],
            shapes: dict[str, list[int]], kinds: dict[str, int],
            put_blob: PutBlob, scene: pb.Scene, loadable: Path) -> list[pb.JobResult]:
    """For each chosen (which, iteration, loss, values): the parameters, the renders per sensor
    (initial, optimized, reference, |optimized - reference|) and optimized textures as images.
    Initial and reference images are made once and shared."""
    spp = max(RESULT_SPP, opt.spp)
    shared = {}
    for sensor, ref in opt.references.items():
        reference = np.array(ref.image, dtype=np.float32)
        shared[sensor] = (reference, [
            _image(put_blob, opt.render(opt.initial, sensor, spp), sensor, "initial"),
            _image(put_blob, reference, sensor, "reference")])
    initial = values_to_proto(opt.initial, shapes, put_blob)
    out = []
    for which, iteration, loss, values in chosen:
        res = pb.JobResult(job=job, which=which, iteration=iteration, loss=loss,
                           parameters=values_to_proto(values, shapes, put_blob),
                           initial_parameters=initial)
        for sensor, (reference, (first, ref_image)) in shared.items():
            optimized = opt.render(values, sensor, spp)
            error = np.abs(optimized - reference) * opt.references[sensor].mask()
            res.images.extend([first, _image(put_blob, optimized, sensor, "optimized"),
                               ref_image, _image(put_blob, error, sensor, "error")])
        for key, v in values.items():
            if kinds.get(key) == pb.TEXTURE and len(shapes[key]) == 3:
                texture = v.reshape(shapes[key])
                if texture.shape[2] == 1:
                    texture = np.repeat(texture, 3, axis=2)
                image = _image(put_blob, texture[..., :3], 0, "texture")
                image.parameter = key
                res.images.append(image)
        _scene_bundle(opt, scene, loadable, values, shapes, put_blob, res)
        out.append(res)
    return out

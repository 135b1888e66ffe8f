"""An engine's outputs as the store keeps them: images as two blobs each (OpenEXR, PNG),
parameter values inline when small and as .npy blobs when large, a result's optimized scene as
a bundle beside the original files."""

from __future__ import annotations

from typing import Callable

import numpy as np

from .. import engine_api as api
from ..records import BundleFile, ImageRef, JobRecord, ResultRecord, SceneRecord
from ..settings import Values, npy

Put = Callable[[bytes], str]  # bytes -> digest, written for the job's owner


def keep_image(image: api.Image, put: Put) -> ImageRef:
    return ImageRef(image.sensor, image.role, image.width, image.height, put(image.exr),
                    put(image.png), image.parameter)


def keep_values(values: dict[str, np.ndarray], shapes: dict[str, list[int]], put: Put
                ) -> dict[str, Values]:
    out = {}
    for key, v in values.items():
        flat = np.asarray(v, dtype=np.float32).ravel()
        out[key] = (Values(flat.tolist()) if flat.size <= api.SMALL
                    else Values(sha256=put(npy(flat, shapes.get(key, [])))))
    return out


def keep_result(job: str, result: api.Result, shapes: dict[str, list[int]],
                scene: SceneRecord, images: list[ImageRef], put: Put) -> ResultRecord:
    """``images``: the per-sensor images made before (the end phase's), which go first; the
    result's own (textures) follow. The optimized scene's new files go next to the original
    main XML."""
    base = scene.main_file.rpartition("/")[0]
    new = {f"{base}/{path}" if base else path: put(data)
           for path, data in result.scene_files.items()}
    files = [f for f in scene.files if f.path not in new]
    files += [BundleFile(path, sha) for path, sha in new.items()]
    return ResultRecord(
        job=job, which=result.which, iteration=result.iteration, loss=result.loss,
        values=keep_values(result.values, shapes, put),
        initial=keep_values(result.initial_values, shapes, put), shapes=dict(shapes),
        images=images + [keep_image(i, put) for i in result.images], scene_files=files,
        scene_file=f"{base}/{result.scene_file}" if base else result.scene_file,
        unplaced=list(result.unplaced),
        gains={s: np.asarray(g, dtype=np.float32).ravel().tolist()
               for s, g in sorted(result.gains.items())},
        standard_errors=dict(result.standard_errors), gain_errors=dict(result.gain_errors))


def results_from_history(job: JobRecord, history: list[api.IterationRecord]
                         ) -> list[ResultRecord]:
    """A job's "best" and "last" as its reported iterations left them, without a renderer:
    what a job stopped in the middle of an iteration (a cancel that stopped its worker) keeps,
    and what a paused or interrupted job shows. Only the values that travel in iteration
    records (parameters of at most ``engine_api.SMALL`` components, the gains) are there; no
    renders and no optimized scene, which need a worker."""
    if not history:
        return []
    by_iteration = {r.iteration: r for r in history}
    first = by_iteration.get(0)
    chosen = [("best", by_iteration.get(job.best_iteration), job.best_loss),
              ("last", history[-1], history[-1].loss)]
    out = []
    for which, record, loss in chosen:
        if record is None:
            continue
        out.append(ResultRecord(
            job=job.name, which=which, iteration=record.iteration, loss=float(loss),
            values=keep_values(record.values, job.shapes, _no_blobs),
            initial=keep_values(first.values, job.shapes, _no_blobs) if first else {},
            shapes=dict(job.shapes), images=[], scene_files=[], scene_file="",
            unplaced=[],
            gains={s: np.asarray(g, dtype=np.float32).ravel().tolist()
                   for s, g in sorted(record.gains.items())}))
    return out


def _no_blobs(data: bytes) -> str:
    raise AssertionError("iteration records hold only values small enough to keep inline")

"""An engine's outputs as the store keeps them: images as two blobs each (OpenEXR, PNG),
parameter values inline when small and as .npy blobs when large, a result's optimized scene as
a bundle beside the original files."""

from __future__ import annotations

from typing import Callable

import numpy as np

from .. import engine_api as api
from ..records import BundleFile, ImageRef, ResultRecord, SceneRecord
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

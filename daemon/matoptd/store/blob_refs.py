"""Which blobs a scene or a job names: what a user may not delete while the scene or job
exists, and what a data dir made before blobs had owners gives each user (see store.py).

Digests are returned bare (no ``blobs/`` prefix), the form the store keys them by.
"""

from __future__ import annotations

import json
from typing import Iterable

from matopt_api.v1 import matopt_pb2 as pb


def _bare(names: Iterable[str]) -> set[str]:
    return {n.removeprefix("blobs/") for n in names if n}


def scene_blobs(scene: pb.Scene, inputs: str | None) -> set[str]:
    """The bundle's files and what the daemon stored for the scene: the prepared XML (and the
    built-in Cornell box), which only the scene's inputs (engine_api.SceneInput as JSON) name."""
    files = json.loads(inputs)["files"].values() if inputs else ()
    return _bare([*(f.sha256 for f in scene.files), *files])


def spec_blobs(spec: pb.JobSpec) -> set[str]:
    """What a job reads: references and their masks, initial values and ground truth given
    as blobs."""
    return _bare([*(r.blob for r in spec.references),
                  *(r.mask_blob for r in spec.references),
                  *(p.initial_blob for p in spec.parameters),
                  *(t.blob for t in spec.ground_truth)])


def result_blobs(result: pb.JobResult) -> set[str]:
    """What the daemon wrote for a job's result: images, large parameter values, and the
    optimized scene's bundle (with the original files it reuses)."""
    return _bare([*(b for i in result.images for b in (i.exr_blob, i.png_blob)),
                  *(v.blob for v in (*result.parameters, *result.initial_parameters)),
                  *(f.sha256 for f in result.scene_files)])


def job_blobs(job: pb.Job, results: Iterable[pb.JobResult], checkpoint: str | None) -> set[str]:
    """``checkpoint``: the blob that held the job's checkpoint in data dirs of the first
    release (later ones keep it as a file outside the blobs)."""
    out = spec_blobs(job.spec) | _bare([checkpoint or ""])
    for result in results:
        out |= result_blobs(result)
    return out

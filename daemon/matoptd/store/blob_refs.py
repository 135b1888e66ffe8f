"""Which blobs a scene or a job names: what a user may not delete while the scene or job
exists, and what a data dir made before blobs had owners gives each user (``Blobs.adopt``).
Digests are bare (no ``blobs/`` prefix), the form the store keys them by."""

from __future__ import annotations

from typing import Iterable

from ..records import JobRecord, ResultRecord, SceneRecord
from ..settings import JobSettings


def _named(digests: Iterable[str]) -> set[str]:
    return {d for d in digests if d}


def scene_blobs(scene: SceneRecord) -> set[str]:
    """The bundle's files and what the daemon stored for the scene: the prepared XML (and the
    built-in Cornell box), which only the scene's inputs name."""
    inputs = scene.inputs.files.values() if scene.inputs is not None else ()
    return _named([*(f.sha256 for f in scene.files), *inputs])


def settings_blobs(settings: JobSettings) -> set[str]:
    """What a job reads besides its scene: references and their masks, initial values and
    ground truth given as blobs."""
    return _named([*(r.sha256 for r in settings.references),
                   *(r.mask_sha256 for r in settings.references),
                   *(p.initial.sha256 for p in settings.parameters if p.initial is not None),
                   *(t.sha256 for t in settings.truth.values())])


def result_blobs(result: ResultRecord) -> set[str]:
    """What the daemon wrote for a job's result: images, large parameter values, and the
    optimized scene's bundle (with the original files it reuses)."""
    return _named([*(b for i in result.images for b in (i.exr, i.png)),
                   *(v.sha256 for v in (*result.values.values(), *result.initial.values())),
                   *(f.sha256 for f in result.scene_files)])


def job_blobs(job: JobRecord, results: Iterable[ResultRecord]) -> set[str]:
    out = settings_blobs(job.settings)
    if job.ending is not None:  # result images made before its results were
        out |= _named(b for images in job.ending.images.values() for i in images
                      for b in (i.exr, i.png))
    for result in results:
        out |= result_blobs(result)
    return out

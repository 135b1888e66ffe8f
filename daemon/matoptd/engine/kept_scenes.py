"""A worker's last job scene, kept loaded after the job is released, for the next job on it.

Loading a scene again gives its objects new Dr.Jit instance ids whenever any other instance
lives meanwhile (a scene kept for another job, a preview), and those ids are part of the IR
of every kernel that dispatches over BSDFs or emitters: Dr.Jit's kernel cache, in memory and
on disk, misses and the job's first iteration compiles again (0.15-1.5 s on 2 CPU cores for
the Cornell box, against 20 ms when the loaded scene is taken again). Keeping the scene also
saves the load itself.

A kept scene also keeps what a job made for it that the next job can use as it is
(``shelf``): its integrator and its frozen iteration's recordings (engine/frozen.py). The next
job with the same integrator and structure replays the recording from its iteration 0 rather
than tracing and recording the iteration again, which is most of a small iteration's cost.

A kept scene is never shared: ``take`` hands it to one job, and only ``give_back`` (at that
job's release) keeps it again, with every value a job can set put back as loaded. At most one
is kept, and one on another scene is dropped before a job loads its own, so that no idle
scene's instances swell another job's kernels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi

# The most parameter data (textures, grids, meshes) a kept scene may hold: an idle worker
# should hold little more than it did at its start. A 1k RGB float texture (12 MiB) is over.
KEEP_BYTES = 8 << 20


@dataclass
class Loaded:
    """A scene as ``load`` made it, with a copy of every settable value (the copies share
    Dr.Jit's buffers, so they cost nothing until a job sets the value in place)."""

    scene: mi.Scene
    key: tuple
    values: dict[str, object]
    # What jobs on this scene leave for the next (the integrator, the frozen function), by
    # name; it goes with the scene.
    shelf: dict[str, object] = field(default_factory=dict)

    @classmethod
    def of(cls, scene: mi.Scene, key: tuple) -> Loaded:
        params = mi.traverse(scene)
        values = {k: _copy(params[k]) for k in params.keys()
                  if not params.flags(k) & mi.ParamFlags.ReadOnly}
        return cls(scene, key, values)

    def restore(self) -> None:
        """Puts back the values a job changed (its parameters, its films' sizes); the scene
        updates only what changed (a moved mesh rebuilds its acceleration structure)."""
        params = mi.traverse(self.scene)
        changed = False
        for key, value in self.values.items():
            if not _same(params[key], value):
                params[key] = _copy(value)
                changed = True
        if changed:
            params.update()

    def nbytes(self) -> int:
        return sum(_nbytes(v) for v in self.values.values())


class KeptScenes:
    """At most one idle loaded scene, by key (the scene's content, overrides and the keys it
    was loaded for, which decide how its meshes were merged)."""

    def __init__(self, limit: int = KEEP_BYTES) -> None:
        self.limit = limit
        self._kept: Loaded | None = None

    def take(self, key: tuple) -> Loaded | None:
        """The kept scene for ``key``, no longer kept; None (and nothing kept any more)
        when the kept one is another scene's."""
        kept, self._kept = self._kept, None
        return kept if kept is not None and kept.key == key else None

    def give_back(self, loaded: Loaded) -> None:
        """Keeps ``loaded``, restored, in place of any other; a scene too large to keep, or
        one that cannot be restored, is dropped."""
        self._kept = None
        if loaded.nbytes() > self.limit:
            return
        try:
            loaded.restore()
        except Exception:  # noqa: BLE001 - a scene not as loaded is never handed out again
            return
        self._kept = loaded

    def drop(self) -> None:
        self._kept = None

    @property
    def kept(self) -> Loaded | None:
        return self._kept


def _copy(value: object) -> object:
    """A new handle on the same value: Mitsuba sets JIT arrays in place, so the scene's own
    object would change with it."""
    return type(value)(value) if dr.is_array_v(value) else value


def _same(a: object, b: object) -> bool:
    ids = dr.detail.collect_indices(a)
    if ids or dr.detail.collect_indices(b):
        return ids == dr.detail.collect_indices(b)
    return bool(dr.all(a == b, axis=None)) if dr.is_array_v(a) else a == b


def _nbytes(value: object) -> int:
    shape = dr.shape(value) if dr.is_jit_v(value) else None
    return 4 * math.prod(int(n) for n in shape) if shape else 0

"""A sensor group's render, loss and backward pass as one frozen function (``dr.freeze``):
traced and recorded once per structure, then replayed, its kernels launched without Python
tracing them again. Most of a small iteration is that tracing.

What keeps a replay equal to the unfrozen iteration:

- The seeds go in as opaque ``mi.UInt32`` (a Python int is part of the recording's key); the
  spp, the sensors and the loss are Python values of the key: a new spp phase records again.
- The backward pass begins inside. Its inputs are the scene's parameters as AD leaves
  (``leaf``): detached copies of v = decode(expand(u)) with gradients on. The maps between
  u and v stay outside, so a multires level (u's shape) does not touch the recording, and
  ``backward`` carries the leaves' gradients on to u through them (plus the choices' loss
  terms, smoothness), as ``dr.backward`` of the whole would.
- The film, the integrator and the scene are made outside and never inside.
- A choice that reads the iteration's renders (eta by differences) gets them as the
  function's outputs, detached; its own renders at other values (eta +- h) are other
  frozen functions' (``renders.Renders.frozen``), the values set outside and read from the
  scene, an argument.

A structure here: the spp, the integrator object, the films' sizes. When it changes, the old
recordings are dropped and the job's notes say that it recorded again and why.
"""

from __future__ import annotations

import gc

import drjit as dr
import mitsuba as mi

from .renders import image_loss, render_images

# The integrators whose iteration replays as recorded: the projective ones sample silhouette
# edges into arrays of data-dependent size (compressions), which a recording cannot replay.
FREEZABLE = ("prb_basic", "prb", "prbvolpath")
# Parameters that move geometry: their update rebuilds the acceleration structure, and their
# gradients need a projective integrator.
GEOMETRY_KINDS = ("vertex_array", "transform")


def unfreezable(integrator: str, kinds: dict[str, str]) -> str:
    """Why a job with this integrator and these parameter kinds (key -> kind) cannot run
    frozen, in words; "" when it can."""
    moving = sorted(k for k, kind in kinds.items() if kind in GEOMETRY_KINDS)
    if moving:
        return (f"{', '.join(moving)} move geometry: each step rebuilds the scene's "
                "acceleration structure, which a frozen function must not do")
    if integrator not in FREEZABLE:
        return (f"the integrator {integrator} samples silhouette edges into arrays of "
                "data-dependent size, which a recording cannot replay")
    return ""


def _group_loss(scene, params, integrator, sensors, seeds, targets, weights, spp, divisor,
                fn, clamp, keep):
    """The loss of a group of sensors (their sum over ``divisor``), back-propagated to the
    scene's parameters, and each sensor's renders, detached, where ``keep`` (for a choice
    that reads them: eta by differences); the function that is frozen."""
    total, kept = 0, []
    for sensor, drawn, target, weight in zip(sensors, seeds, targets, weights):
        images = render_images(scene, params, integrator, sensor, spp, drawn)
        total += image_loss(fn, clamp, images, target, weight)
        if keep:
            kept.append([dr.detach(img) for img in images])
    total /= divisor
    dr.backward(total)
    return dr.detach(total), kept


def call(fn, *args):
    """``fn(*args)``, a frozen function, with Python's collector off: freeing another job's
    scene inside a recording enqueues a host function, which a recording refuses by aborting
    the process."""
    collecting = gc.isenabled()
    gc.disable()
    try:
        return fn(*args)
    finally:
        if collecting:
            gc.enable()


def _detached_images(scene, params, integrator, sensor, spp, seeds):
    with dr.suspend_grad():
        return render_images(scene, params, integrator, sensor, spp, seeds)


class FrozenLoss:
    """What the loop asks instead of rendering: ``leaf(key, v)`` (what the scene holds of v),
    a call (a group's loss, its gradient on the leaves) and ``backward`` (on to u)."""

    def __init__(self, ctx) -> None:
        self.ctx = ctx
        self.fn = dr.freeze(_group_loss, warn_after=1000)
        self.images = dr.freeze(_detached_images, warn_after=1000)
        self.pairs: dict[str, tuple[object, object]] = {}  # key -> (v, the scene's leaf)
        self.structure: tuple | None = None
        self.stale = False    # the leaves hold a gradient not (yet) carried on
        self.recordings = 0   # recordings made (Dr.Jit's count, over every structure)

    def leaf(self, key: str, value):
        """v as the scene holds it: detached, gradients on (the recording's input)."""
        leaf = dr.detach(value)
        dr.enable_grad(leaf)
        self.pairs[key] = (value, leaf)
        self.stale = False
        return leaf

    def _structure(self) -> tuple:
        ctx = self.ctx
        films = tuple(tuple(int(n) for n in s.film().size()) for s in ctx.scene.sensors())
        return ctx.spp, id(ctx.integrator), films

    def _changed(self, structure: tuple) -> str:
        """What changed from the last structure, in words."""
        (spp0, integrator0, films0), (spp, integrator, films) = self.structure, structure
        return "; ".join(
            ([f"spp {spp0} -> {spp}"] if spp0 != spp else [])
            + (["another integrator"] if integrator0 != integrator else [])
            + (["film size"] if films0 != films else []))

    def __call__(self, group: list[tuple[int, int]], divisor: float):
        """The loss of ``group`` ((slot, sensor) pairs) over ``divisor``, at this iteration's
        seeds and spp, its gradient on the leaves."""
        ctx = self.ctx
        structure = self._structure()
        if structure != self.structure:
            if self.structure is not None:
                ctx.note(f"frozen: iteration {ctx.iteration} recorded again "
                         f"({self._changed(structure)})")
                self.fn.clear()
                self.images.clear()
            self.structure = structure
        if self.stale:  # a loss taken without a step (the last iteration, a skipped one)
            for _, leaf in self.pairs.values():
                dr.clear_grad(leaf)
        refs = [ctx.references[sensor] for _, sensor in group]
        before = self.fn.n_recordings
        keep = ctx.keeps_images
        total, images = call(
            self.fn, ctx.scene, ctx.params, ctx.integrator, tuple(s for _, s in group),
            [[dr.opaque(mi.UInt32, s) for s in ctx.seeds(n)] for n, _ in group],
            [r.image for r in refs], [r.weight for r in refs], ctx.spp, float(divisor),
            ctx.loss.fn, bool(ctx.settings.clamp), keep)
        if keep:
            ctx.images.update({sensor: kept for (_, sensor), kept in zip(group, images)})
        self.recordings += self.fn.n_recordings - before
        self.stale = True
        return total

    def render(self, scene, params, integrator, sensor: int, spp: int, seeds: list[int]
               ) -> list:
        """``renders.render_images``, detached, replayed (a choice's renders at other values,
        set outside: the scene is an argument, read afresh at each replay)."""
        before = self.images.n_recordings
        out = call(self.images, scene, params, integrator, sensor, spp,
                   [dr.opaque(mi.UInt32, s) for s in seeds])
        self.recordings += self.images.n_recordings - before
        return out

    def backward(self, extra) -> None:
        """The leaves' gradients on to Adam's variables through the maps, with the gradient
        of ``extra`` (the choices' loss terms; a float: none), as one backward pass."""
        for value, leaf in self.pairs.values():
            dr.accum_grad(value, dr.grad(leaf))
            dr.enqueue(dr.ADMode.Backward, value)
            dr.clear_grad(leaf)
        if not isinstance(extra, (int, float)):
            dr.set_grad(extra, 1.0)
            dr.enqueue(dr.ADMode.Backward, extra)
        dr.traverse(dr.ADMode.Backward)
        self.stale = False

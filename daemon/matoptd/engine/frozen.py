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

A structure here: the spp, the integrator object, the films' sizes. Each has recordings of its
own, and a scene keeps those of its last KEPT_STRUCTURES structures: jobs at other spp or film
sizes that take turns on a scene (users sharing it, a spp schedule) replay rather than record
again. When the structure changes, the job's notes say so, why, and whether it replays or
records.

A recording replays only for inputs laid out as when it was made, and renders outside these
functions (a job's standard errors' passes) leave the scene otherwise than an iteration
does: its films' storage, and literals (constants) set to other values. So the
films are emptied before each call (``fresh_films``) and every input is opaque from the first
recording on (``auto_opaque=False``; by default a literal that changes between calls is made
opaque by recording again, which cost the second job on a scene 0.6-0.8 s of compiles).

The frozen functions, by structure, stay on a kept scene's shelf (kept_scenes.py) for the
next job on it: with the same integrator (the shelf's) and a structure kept, that job's
iteration 0 and its result images replay the recordings instead of tracing and recording again.

On a scene just loaded, each sensor group's first call runs unfrozen: a render leaves state in
the scene (its film's, its sampler's) that is among the recording's inputs, so a recording
made before any render is laid out as no later call is, and would never replay. The first
event of such a job comes after an unfrozen iteration rather than a recording (which costs
about 2.5 of them).
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
# The structures whose recordings a scene keeps (the most recently used): each holds its
# kernels and launch plan, so a scene's memory grows with the structures it keeps.
KEPT_STRUCTURES = 4


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


class _Holder:
    """The job's SceneParameters, behind an object that stays the same from job to job.

    Dr.Jit cannot look into a SceneParameters, so a recording's key holds the object itself:
    a new job's (a new traversal) would record again, or replay by chance where Python gave
    the new object the old one's address. Its values reach the recording through the scene,
    which is traversed; the object only names what the render differentiates."""

    __slots__ = ("params",)

    def __init__(self) -> None:
        self.params = None


def _group_loss(scene, holder, integrator, sensors, seeds, targets, weights, spp, divisor,
                fn, clamp, keep):
    """The loss of a group of sensors (their sum over ``divisor``), back-propagated to the
    scene's parameters, and each sensor's renders, detached, where ``keep`` (for a choice
    that reads them: eta by differences); the function that is frozen."""
    total, kept = 0, []
    for sensor, drawn, target, weight in zip(sensors, seeds, targets, weights):
        images = render_images(scene, holder.params, integrator, sensor, spp, drawn)
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


def fresh_films(scene) -> None:
    """Each sensor's film emptied, as a render's first step empties it. A film's storage is
    among a recording's inputs, laid out as the last render left it: one made outside the
    frozen functions (a result image, J's renders) would make the next job's iteration 0
    record and compile again rather than replay."""
    for sensor in scene.sensors():
        sensor.film().prepare([])


def freeze(fn):
    """``fn`` frozen, every input opaque from the first recording on: what changes from call
    to call is opaque already, and Dr.Jit would otherwise record again to find that out."""
    return dr.freeze(fn, warn_after=1000, auto_opaque=False)


def _detached_images(scene, integrator, sensor, spp, seeds):
    # No SceneParameters: a recording's key would hold the job's own (see _Holder), and a
    # detached render needs none.
    with dr.suspend_grad():
        return render_images(scene, None, integrator, sensor, spp, seeds)


class FrozenLoss:
    """What the loop asks instead of rendering: ``leaf(key, v)`` (what the scene holds of v),
    a call (a group's loss, its gradient on the leaves) and ``backward`` (on to u)."""

    def __init__(self, ctx) -> None:
        self.ctx = ctx
        # structure -> (the iteration's frozen function, the detached renders': eta +- h,
        # result images; the integrator, held so that its id, in the structure, is no other
        # object's), least recently used first, as jobs before on this scene left them
        self.kept: dict[tuple, tuple] = ctx.shelf.setdefault("frozen", {})
        self.holder = ctx.shelf.setdefault("frozen holder", _Holder())
        self.taken = bool(self.kept)  # a recording made by a job before may replay
        self.structure = next(reversed(self.kept), None)  # the scene's last, for the notes
        self.fn = self.images = None  # the structure's, from this job's first call (_use)
        self.pairs: dict[str, tuple[object, object]] = {}  # key -> (v, the scene's leaf)
        self.stale = False    # the leaves hold a gradient not (yet) carried on
        self.recordings = 0   # recordings made by this job (Dr.Jit's count, every structure)
        self.replayed = 0     # calls that replayed a recording (this job's or one taken)
        # sensor groups rendered since the scene was loaded (unfrozen, their first time)
        self.rendered: set[tuple[int, ...]] = set()

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

    def _use(self) -> None:
        """The frozen functions of the current structure: the scene's kept ones, else new;
        kept in their turn, the least recently used beyond KEPT_STRUCTURES dropped."""
        structure = self._structure()
        if self.fn is not None and structure == self.structure:
            return
        for other in [s for s in self.kept if s[1] != structure[1]]:
            del self.kept[other]  # made with an integrator the scene no longer holds
        fns = self.kept.pop(structure, None)
        if self.structure is not None and structure != self.structure:
            done = "replays its structure's recording" if fns else "recorded again"
            self.ctx.note(f"frozen: iteration {self.ctx.iteration} {done} "
                          f"({self._changed(structure)})")
        self.kept[structure] = fns or (freeze(_group_loss), freeze(_detached_images),
                                       self.ctx.integrator)
        while len(self.kept) > KEPT_STRUCTURES:
            del self.kept[next(iter(self.kept))]
        self.fn, self.images, _ = self.kept[structure]
        self.structure = structure

    def __call__(self, group: list[tuple[int, int]], divisor: float):
        """The loss of ``group`` ((slot, sensor) pairs) over ``divisor``, at this iteration's
        seeds and spp, its gradient on the leaves."""
        ctx = self.ctx
        self._use()
        if self.stale:  # a loss taken without a step (the last iteration, a skipped one)
            for _, leaf in self.pairs.values():
                dr.clear_grad(leaf)
        refs = [ctx.references[sensor] for _, sensor in group]
        before = self.fn.n_recordings
        sensors = tuple(s for _, s in group)
        fn = self.fn if self.taken or sensors in self.rendered else _group_loss
        self.rendered.add(sensors)
        keep = ctx.keeps_images
        fresh_films(ctx.scene)
        self.holder.params = ctx.params
        try:
            total, images = call(
                fn, ctx.scene, self.holder, ctx.integrator, sensors,
                [[dr.opaque(mi.UInt32, s) for s in ctx.seeds(n)] for n, _ in group],
                [r.image for r in refs], [r.weight for r in refs], ctx.spp, float(divisor),
                ctx.loss.fn, bool(ctx.settings.clamp), keep)
        finally:
            self.holder.params = None  # the job's, not the shelf's to keep
        if keep:
            ctx.images.update({sensor: kept for (_, sensor), kept in zip(group, images)})
        if fn is self.fn:
            made = self.fn.n_recordings - before
            if self.taken and not (self.recordings or self.replayed or made):
                ctx.note(f"frozen: iteration {ctx.iteration} replayed the recording a job "
                         "before made on this scene: nothing traced or recorded")
            self.recordings += made
            self.replayed += not made
        self.stale = True
        return total

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

    def render(self, scene, params, integrator, sensor: int, spp: int, seeds: list[int]
               ) -> list:
        """``renders.render_images``, detached, replayed (a choice's renders at other values,
        a job's result images: set outside, the scene is an argument, read afresh at each
        replay); ``params`` unused (a detached render differentiates nothing)."""
        self._use()
        before = self.images.n_recordings
        fresh_films(scene)
        out = call(self.images, scene, integrator, sensor, spp,
                   [dr.opaque(mi.UInt32, s) for s in seeds])
        self.recordings += self.images.n_recordings - before
        return out

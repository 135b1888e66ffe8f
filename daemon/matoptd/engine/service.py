"""``engine_api.Engine`` implemented with Mitsuba: what a worker process runs.

Inputs arrive by digest and are fetched once into the worker's own cache (verified, read-only),
where a scene's bundle is laid out as links to them; nothing here reads the daemon's data
directory. A job's ``Optimization`` stays in memory between ``start`` and ``release``.
"""

from __future__ import annotations

import copy
import ctypes
import gc
import hashlib
import os
import posixpath
import shutil
import tempfile
import time
import uuid
from dataclasses import dataclass
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from .. import engine_api as api
from ..settings import Values, read_values
from . import (choices, diagnosis, images, parameters, probes, scene as scenes, scene_export,
               uncertainty, verdicts)
from .integrator import medium_notes
from .jacobian import Pieces
from .kept_scenes import KeptScenes, Loaded
from .optimize import Best, CheckpointError, Optimization, Reference


@dataclass
class Run:
    """A job's optimization, loaded."""

    opt: Optimization
    main_xml: Path              # the prepared XML it was loaded from (for the scene export)
    overrides: dict[str, str]
    shapes: dict[str, list[int]]
    kinds: dict[str, str]
    max_samples: int = 0  # of one render call (settings.max_samples)
    scene: Loaded | None = None  # the scene as loaded, kept again at release (unless replaced)
    estimating: Pieces[dict[str, uncertainty.Estimate]] | None = None  # the end's, under way
    estimated: dict[str, uncertainty.Estimate] | None = None  # ... and done, for ``finish``


class MitsubaEngine:
    """One worker's engine. ``cache`` holds fetched blobs and laid-out scenes."""

    def __init__(self, fetch: api.Fetch, cache: Path) -> None:
        self.fetch = fetch
        self.cache = Path(cache)
        (self.cache / "blobs").mkdir(parents=True, exist_ok=True)
        (self.cache / "scenes").mkdir(parents=True, exist_ok=True)
        self.runs: dict[str, Run] = {}
        self._preview: tuple[str, mi.Scene] | None = None  # the last scene rendered
        self.kept = KeptScenes()  # the last released job's scene, for the next job on it

    # -- inputs -----------------------------------------------------------------------------

    def blob(self, sha256: str) -> Path:
        """The local, verified, read-only copy of a blob, fetched on first use."""
        path = self.cache / "blobs" / sha256
        if path.exists():
            return path
        data = self.fetch(sha256)
        if hashlib.sha256(data).hexdigest() != sha256:
            raise api.EngineError(f"blob {sha256} arrived corrupted (its content hashes "
                                  "differently); nothing was loaded from it")
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".fetch-")
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.chmod(tmp, 0o444)
        os.replace(tmp, path)
        return path

    def layout(self, scene: api.SceneInput) -> Path:
        """The bundle as a directory of links into the blob cache; returns the main XML.

        Laid out under a temporary name and renamed into place, so a directory that exists is
        complete. Files are links to read-only blobs: nothing is ever written through them."""
        directory = self.cache / "scenes" / scene.key
        if not directory.exists():
            tmp = self.cache / "scenes" / f".{scene.key}.{uuid.uuid4().hex[:8]}"
            for path, sha in scene.files.items():
                norm = posixpath.normpath(path)
                if norm.startswith(("/", "../")) or norm == "..":
                    raise api.InvalidInput(f"bundle path '{path}' leaves the bundle")
                dest = tmp / norm
                dest.parent.mkdir(parents=True, exist_ok=True)
                os.link(self.blob(sha), dest)
            try:
                os.rename(tmp, directory)
            except OSError:  # another worker laid it out meanwhile
                shutil.rmtree(tmp, ignore_errors=True)
        return directory / scene.main_file

    def load(self, scene: api.SceneInput, keys: list[str] | None = None) -> mi.Scene:
        return scenes.load(self.layout(scene), scene.overrides, scene.display, keys,
                           root=self.cache / "scenes" / scene.key)

    # -- scene tasks ------------------------------------------------------------------------

    def describe_scene(self, scene: api.SceneInput) -> api.SceneDescription:
        loaded = self.load(scene)
        d = scenes.describe(loaded)
        params = mi.traverse(loaded)
        return api.SceneDescription(
            [api.SensorInfo(i, sid, w, h) for i, (sid, w, h) in enumerate(d.sensors)],
            d.has_media, [parameters.listing(info, params[info.key]) for info in d.parameters])

    def render(self, scene: api.SceneInput, request: api.RenderRequest) -> list[api.Image]:
        """Renders with the scene's own integrator, parameters overridden, then restored."""
        if self._preview is None or self._preview[0] != scene.key:
            self._preview = None
            self._preview = (scene.key, self.load(scene))
        loaded = self._preview[1]
        count = len(loaded.sensors())
        sensors = request.sensors or list(range(count))
        for s in sensors:
            if not 0 <= s < count:
                raise api.InvalidInput(f"sensor {s} does not exist: the scene has {count} "
                                       "sensor(s)")
        params = mi.traverse(loaded)
        # Only differentiable float values: an integer buffer (a mesh's faces) set to other
        # numbers would make the renderer index memory it does not own.
        settable = {info.key for info in parameters.describe(params)}
        saved = {}
        try:
            for key, v in request.values.items():
                if key not in settable:
                    raise api.InvalidInput(f"parameter '{key}' cannot be set: it is not one of "
                                           "the scene's differentiable parameters")
                saved[key] = parameters.flat(params[key])
                try:
                    params[key] = parameters.assign(params[key], v)
                except ValueError as exc:
                    raise api.InvalidInput(f"parameter '{key}': {exc}") from None
            params.update()
            # A scene without <integrator> renders with Mitsuba's default, the path tracer.
            integrator = loaded.integrator() or mi.load_dict({"type": "path"})
            out = []
            for s in sensors:
                img = mi.render(loaded, sensor=s, integrator=integrator, seed=request.seed,
                                spp=request.spp)
                out.append(image(np.array(img, dtype=np.float32), s, "render"))
            return out
        finally:
            for key, v in saved.items():
                params[key] = parameters.assign(params[key], v)
            params.update()

    def check_references(self, references: list[api.ReferenceInput]) -> None:
        for r in references:
            images.load_reference(r, self._blob_path)

    def _blob_path(self, sha256: str) -> str:
        return str(self.blob(sha256))

    def _values(self, values: Values, what: str) -> np.ndarray:
        """Values a job gives, inline or (large ones) fetched by digest."""
        try:
            return read_values(values, lambda sha: self.blob(sha).read_bytes(), what)
        except ValueError as exc:
            raise api.InvalidInput(str(exc)) from None

    # -- jobs -------------------------------------------------------------------------------

    def start(self, job: str, settings: api.JobSettings, checkpoint: bytes | None
              ) -> api.Started:
        """Builds the job's optimization, on the scene a released job left when it is the
        same one (loaded for the same keys), else on a new load. A scene kept for previews or
        for another scene's jobs goes first: Mitsuba dispatches a BSDF's or an emitter's
        virtual call over every live instance in the process, so each scene held makes every
        job's kernels bigger, and a scene loaded beside it gets other instance ids, which
        the kernel cache sees as other kernels."""
        self._preview = None
        self._park_others()
        began = time.perf_counter()
        keys = [p.key for p in settings.parameters]
        key = (settings.scene.key, tuple(keys))
        held = self.kept.take(key)
        if held is None:
            held = Loaded.of(self.load(settings.scene, keys), key)
        loaded = held.scene
        chosen = choices.build(settings)
        loading = choices.Loading(self.layout(settings.scene), lambda path: scenes.load(
            path, settings.scene.overrides, settings.scene.display, keys,
            root=self.cache / "scenes" / settings.scene.key))
        for c in chosen:
            loaded = c.prepare_scene(loaded, loading)
        notes = loading.notes
        shelf = held.shelf if loaded is held.scene else None  # what jobs before left
        refs = _references(loaded, settings, self._blob_path, notes, shelf)
        listed = {i.key: i for i in parameters.describe(mi.traverse(loaded))}
        try:
            truth = {k: self._values(v, f"ground truth of '{k}'")
                     for k, v in settings.truth.items()}
            initial = {p.key: self._values(p.initial, f"initial value of '{p.key}'")
                       for p in settings.parameters if p.initial is not None}
            probed: list[api.IterationRecord] = []
            if checkpoint is None and settings.starts > 1:
                # Each probe's loop with the choices as prepared for this scene, fresh.
                opt, probed = probes.run(lambda point: Optimization(
                    loaded, settings, refs, copy.deepcopy(chosen), None,
                    {**initial, **point}, truth, shelf), notes)
            else:
                opt = Optimization(loaded, settings, refs, chosen, checkpoint, initial, truth,
                                   shelf)
        except CheckpointError as exc:
            raise api.EngineError(f"the job's checkpoint cannot be restored: {exc}") from None
        skipped = [i for i in range(len(loaded.sensors())) if i not in opt.renders.references]
        changed = [opt.chosen.changed] if opt.chosen.changed else []  # the scene's integrator
        said = [line for c in opt.active for line in c.notes()]  # once, at the start
        opt.notes = notes + changed + said + medium_notes(loaded, keys) + [
            f"gradients for: {', '.join(keys)}",
            f"sensors rendered: {', '.join(map(str, opt.renders.references))}"
            + (f" (not rendered: {', '.join(map(str, skipped))})" if skipped else "")]
        if checkpoint is None:
            opt.progress.elapsed += time.perf_counter() - began
        shapes = {k: list(listed[k].shape) if k in listed else [] for k in keys}
        kinds = {k: listed[k].kind if k in listed else "vector" for k in keys}
        # A choice that loaded the scene anew (filter scaling) leaves nothing to keep.
        self.runs[job] = Run(opt, self.layout(settings.scene), dict(settings.scene.overrides),
                             shapes, kinds, settings.max_samples,
                             held if loaded is held.scene else None)
        p = opt.progress
        return api.Started(p.iteration, opt.integrator_name, opt.integrator_reason,
                           list(opt.renders.references), opt.notes, shapes, kinds, opt.status(),
                           api.Progress(probed, False, "", p.best.iteration, p.best.loss,
                                        p.elapsed, _counters(opt), opt.status())
                           if probed else None)

    def _run(self, job: str) -> Run:
        try:
            return self.runs[job]
        except KeyError:
            raise api.EngineError(f"job '{job}' is not loaded on this worker") from None

    def step(self, job: str, n: int) -> api.Progress:
        run = self._run(job)
        opt = run.opt
        records = []
        done, reason = False, ""
        for _ in range(max(1, n)):
            s = opt.step()
            records.append(probes.iteration_record(opt, s))
            if s.done:
                done, reason = True, s.stop_reason
                break
        # The last step's backward pass stays pending, as in a plain loop: the next iteration
        # (or a checkpoint) evaluates it. The watchdog gives a checkpoint an iteration's time.
        p = opt.progress
        return api.Progress(records, done, reason, p.best.iteration, p.best.loss, p.elapsed,
                            _counters(opt), opt.status())

    def checkpoint(self, job: str) -> bytes:
        return self._run(job).opt.checkpoint()

    def result_images(self, job: str, sensor: int) -> dict[str, list[api.Image]]:
        """One sensor's result images, per result ("best", "last"): initial, optimized,
        reference and |optimized - reference|. One call per sensor, so that the daemon can
        let other jobs run between them (and a cancel end promptly)."""
        run = self._run(job)
        return _sensor_images(run, _chosen(run.opt), sensor)

    def estimate_part(self, job: str, seconds: float) -> bool:
        """The standard errors of the job's end, for about ``seconds`` (one pass of J at the
        least); True once they are done. A turn of its worker each, so that other jobs run
        between them: the estimate may take a minute."""
        run = self._run(job)
        if run.estimated is None:
            self._park_others(run)  # a job may have loaded beside it since its last piece
            if run.estimating is None:
                run.opt.flush()
                run.estimating = uncertainty.estimating(run.opt, _chosen(run.opt), run.kinds,
                                                        run.shapes)
            until = time.perf_counter() + seconds
            try:
                while True:
                    next(run.estimating)
                    if time.perf_counter() >= until:
                        break
            except StopIteration as done:
                run.estimated, run.estimating = done.value, None
        return run.estimated is not None

    def _park_others(self, run: Run | None = None) -> None:
        """Every run but ``run`` parked (Optimization.park): their scenes' AD edges out of the
        forward-mode passes of a run loading or estimating beside them."""
        for other in self.runs.values():
            if other is not run and not other.opt.parked:
                other.opt.park()

    def finish(self, job: str, history: list[api.IterationRecord], cancelled: bool,
               render: bool = True) -> api.Finished:
        """Results for the best and the last iteration run (none before the first), then the
        diagnosis. Renders in results are off the job's clock. Without ``render`` the results
        hold no per-sensor images (``result_images`` made them) but still the textures."""
        run = self._run(job)
        opt = run.opt
        results = _results(run, _chosen(opt), render)
        opt.flush()
        estimates = (run.estimated if run.estimated is not None  # estimate_part made them
                     else uncertainty.of_kept(opt, _chosen(opt), run.kinds, run.shapes))
        shown = estimates.get("best") or estimates.get("last") or uncertainty.Estimate({}, {}, [])
        paths: dict[str, list[list[float]]] = {}
        errors: dict[str, list[float]] = {}
        for record in history:
            for key, v in record.values.items():
                paths.setdefault(key, []).append(np.asarray(v).ravel().tolist())
            for key, e in record.errors.items():
                errors.setdefault(key, []).append(e.relative)
        trajectories = {k: np.array(p) for k, p in paths.items() if len(p) == len(history)}
        # Textures and grids travel as blobs, not in records: their means, as this worker saw
        # them (since the job started here), stand in for them in the trade-off check.
        for key, means in ((k, r.means) for k, r in opt.records.items()):
            if key not in trajectories and len(means) >= 20:
                trajectories[key] = np.array(means)[:, None]
        diagnosed = diagnosis.diagnose(
            opt.kept, opt.progress.last.values, [h.loss for h in history],
            opt.progress.nonfinite_steps, opt.progress.skipped_steps, trajectories,
            {k: e for k, e in errors.items() if len(e) == len(history)},
            {k: r.gradients for k, r in opt.records.items() if r.gradients},
            shown.traded, shown.undetermined)
        # One verdict per component, the diagnosis and the standard errors reconciled: what
        # every surface shows; with the other basins the probes found, where starts were
        # compared.
        found, spans = opt.progress.probes, probes.spans(opt)
        said = verdicts.several(verdicts.reconcile(shown, diagnosed, {}), found, spans)
        for r in results:
            e = estimates.get(r.which)
            final = said if not e else verdicts.several(
                verdicts.reconcile(e, diagnosed, _small(r.values, run.kinds)), found, spans)
            r.standard_errors, r.gain_errors = final.errors, final.gains
        return api.Finished(results, said.notes + opt.said, _counters(opt))

    def estimate(self, run: str, settings: api.JobSettings | None, checkpoint: bytes | None,
                 which: str, seconds: float) -> api.Estimated | None:
        """Standard errors of a paused job's kept iteration ("best" or "last"), as its end
        would estimate them, for about ``seconds`` (one pass of J at the least); None until
        they are done. The job is loaded from its checkpoint as ``run``, a name of its own
        (a resume meanwhile loads the job apart), by the first call or by one that finds it
        gone (its worker restarted), and released when they are done; a call without them
        finding it gone raises. The checkpoint holds no gradient records: the noise is the
        model's and no distance to go is added."""
        if run not in self.runs:
            if settings is None or checkpoint is None:
                raise api.EngineError(f"'{run}' is not loaded on this worker")
            self.start(run, settings, checkpoint)
            loaded = self.runs[run]
            chosen = [c for c in _chosen(loaded.opt) if c[0] == which]
            if not chosen:
                self.release(run)
                raise api.EngineError(f"job '{run.split('#')[0]}' has no {which.upper()} "
                                      "iteration yet")
            loaded.estimating = uncertainty.estimating(loaded.opt, chosen, loaded.kinds,
                                                       loaded.shapes)
        if not self.estimate_part(run, seconds):
            return None
        try:
            opt = self.runs[run].opt
            said = verdicts.several(
                verdicts.reconcile(self.runs[run].estimated[which], diagnosis.Diagnosis(), {}),
                opt.progress.probes, probes.spans(opt))
            return api.Estimated(said.errors, said.gains, said.notes)
        finally:
            self.release(run)

    def release(self, job: str) -> None:
        """Drops the job's run and returns the memory it held: Dr.Jit keeps freed buffers in
        a cache of its own, which goes back only when asked. Its scene is kept, as loaded,
        for the next job on it: the run goes first, so that none of its buffers stay."""
        run = self.runs.pop(job, None)
        if run is not None and run.estimating is not None:
            run.estimating.close()  # its scene held at a kept iteration goes back as it was
        held = run.scene if run is not None else None
        del run
        gc.collect()
        if held is not None:
            self.kept.give_back(held)
            del held
        if not self.runs:
            dr.flush_malloc_cache()
            _trim_heap()


def _trim_heap() -> None:
    """Hands glibc's free arenas back to the system: without it the memory freed by a released
    run stays resident, and the worker looks as if it still held the job."""
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass  # not glibc: the allocator keeps its own policy


def _small(values: dict[str, np.ndarray], kinds: dict[str, str]) -> dict[str, int]:
    """The component count of each value a result gives a verdict per component: those
    shown inline, but textures and grids (their mean level is in the notes)."""
    return {k: int(np.size(v)) for k, v in values.items()
            if np.size(v) <= api.SMALL and kinds.get(k) not in ("texture", "volume_grid")}


def _counters(opt: Optimization) -> api.Counters:
    p = opt.progress
    return api.Counters(p.nonfinite_steps, p.skipped_steps, p.clamped)


def image(pixels: np.ndarray, sensor: int, role: str, parameter: str = "") -> api.Image:
    exr, png = images.encode(pixels)
    return api.Image(sensor, role, pixels.shape[1], pixels.shape[0], exr, png, parameter)


def _film_key(params: mi.SceneParameters, sensor: mi.Sensor) -> str | None:
    key = f"{sensor.id()}.film.size"
    return key if key in params else None


def _references(scene: mi.Scene, settings: api.JobSettings, blob, notes: list[str],
                shelf: dict | None = None) -> dict[int, Reference]:
    """Reads each reference (with its mask) and sizes its sensor's film: height from
    ``settings.film_height`` (or the film's own), width from the reference's aspect ratio. Each
    sensor keeps its own size. Masked and NaN/Inf pixels weigh 0 in every loss; the notes
    count them. A kept scene's ``shelf`` holds the last job's images as read, so the next job
    against the same files does not decode them again."""
    params = mi.traverse(scene)
    sensors = scene.sensors()
    # Sizes before any resize: sensors may share one film, which the first resize changes
    # for all of them, and each sensor's note compares with what its scene declared.
    declared = [tuple(int(x) for x in s.film().crop_size()) for s in sensors]
    refs = {}
    read = (shelf or {}).get("references", {})
    kept = {}
    for r in sorted(settings.references, key=lambda r: r.sensor):
        index, name = r.sensor, r.name
        key = (r.sha256, name, r.alpha_mask, r.mask_sha256, r.mask_name)
        picture, weight, said = kept[key] = read.get(key) or images.load_reference(r, blob)
        notes += said
        film = sensors[index].film().crop_size()
        width, height = api.reference_film(settings.film_height or declared[index][1],
                                           picture.shape[1], picture.shape[0])
        if (width, height) != (int(film[0]), int(film[1])):
            key = _film_key(params, sensors[index])
            if key is None:
                raise api.InvalidInput(f"sensor {index}'s film cannot be resized to "
                                       f"{width}x{height} for reference '{name}'")
            params[key] = mi.ScalarVector2u(width, height)
            params.update()
        if (width, height) != declared[index]:
            notes.append(f"sensor {index} renders {width}x{height} (film was "
                         f"{declared[index][0]}x{declared[index][1]}) to follow "
                         + (f"film height {settings.film_height} and " if settings.film_height
                            else "") + f"reference '{name}' ({picture.shape[1]}x"
                         f"{picture.shape[0]})")
        picture, weight = images.fit(picture, weight, (width, height))
        whole = bool(weight.min() >= 1.0)
        weight = np.repeat(weight[..., None], 3, axis=2)
        refs[index] = Reference(mi.TensorXf(picture), None if whole else mi.TensorXf(weight),
                                r.name)
    if shelf is not None:
        shelf["references"] = kept
    return refs


def _chosen(opt: Optimization) -> list[tuple[str, Best]]:
    """The iterations a job's results show: the best, and the last run (none before the
    first)."""
    p = opt.progress
    chosen = [("best", p.best)] if p.best.iteration >= 0 else []
    if p.last.iteration >= 0:
        chosen.append(("last", p.last))
    return chosen


def _sensor_images(run: Run, chosen: list[tuple[str, Best]], sensor: int
                   ) -> dict[str, list[api.Image]]:
    """One sensor's renders per chosen iteration (initial, optimized, reference,
    |optimized - reference| by mask weight; with gains, optimized renders are times the
    iteration's gain, as the loss saw them); initial and reference are made once and
    shared."""
    opt = run.opt
    ref = opt.renders.references[sensor]
    reference = np.array(ref.image, dtype=np.float32)
    spp = api.result_spp(opt.spp, reference.shape[0] * reference.shape[1], run.max_samples)
    first = image(opt.renders.render(opt.initial, sensor, spp), sensor, "initial")
    ref_image = image(reference, sensor, "reference")
    out: dict[str, list[api.Image]] = {}
    made: dict[int, list[api.Image]] = {}  # a job whose last iteration was its best: one render
    for which, it in chosen:
        if it.iteration not in made:
            optimized = opt.renders.render(it.values, sensor, spp, it.gains)  # as the loss saw it
            error = np.abs(optimized - reference) * ref.mask()
            made[it.iteration] = [first, image(optimized, sensor, "optimized"), ref_image,
                                  image(error, sensor, "error")]
        out[which] = made[it.iteration]
    return out


def _results(run: Run, chosen: list[tuple[str, Best]], render: bool = True
             ) -> list[api.Result]:
    """For each chosen iteration: the renders per sensor (with ``render``), optimized
    textures as images, and the optimized scene."""
    opt = run.opt
    per_sensor = [_sensor_images(run, chosen, s) for s in opt.renders.references] if render else []
    out = []
    for which, it in chosen:
        images_ = [i for sensor in per_sensor for i in sensor[which]]
        for key, v in it.values.items():
            shape = run.shapes[key]
            if run.kinds.get(key) == "texture" and len(shape) == 3:
                texture = v.reshape(shape)
                if texture.shape[2] == 1:
                    texture = np.repeat(texture, 3, axis=2)
                images_.append(image(texture[..., :3], 0, "texture", key))
        with opt.renders.holding(it.values) as held:
            files, unplaced = scene_export.optimized_scene(run.main_xml, run.overrides, held,
                                                           it.values, run.shapes)
        out.append(api.Result(which, it.iteration, it.loss, it.values, opt.initial, images_,
                              files, "scene_optimized.xml", unplaced, it.gains))
    return out

"""A worker keeps the last released job's scene for the next job on it (engine/kept_scenes.py),
in-process on MitsubaEngine: the next job compiles nothing and follows the trajectory it
would follow alone; what a job changed in the scene (its parameters, its film's size) is put
back; two jobs loaded at once on one scene each have their own; another scene's job drops
the kept one."""

from __future__ import annotations

import contextlib
import hashlib
from pathlib import Path

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba")

from matoptd import settings as api  # noqa: E402

RED = "red.reflectance.value"
GREEN = "green.reflectance.value"
XML = Path(__file__).resolve().parents[1] / "daemon" / "matoptd" / "engine" / "cornell_box.xml"


@pytest.fixture(scope="module")
def service():
    mi.set_variant("llvm_ad_rgb")
    from matoptd.engine import service
    return service


@pytest.fixture
def make(service, tmp_path):
    """An engine over blobs held here, and a job's settings on the Cornell box at ``res``
    against a 48x24 reference (the film follows its aspect ratio: 2 res x res)."""
    blobs: dict[str, bytes] = {}

    def put(data: bytes) -> str:
        sha = hashlib.sha256(data).hexdigest()
        blobs[sha] = data
        return sha

    image = mi.render(mi.load_file(str(XML), resx=48, resy=24), spp=16, seed=5)
    mi.Bitmap(image).write(str(tmp_path / "ref.exr"))
    ref = put((tmp_path / "ref.exr").read_bytes())
    xml = put(XML.read_bytes())
    engine = service.MitsubaEngine(blobs.__getitem__, tmp_path / "cache")

    def settings(res: int = 32, initial: bool = True, **kw) -> api.JobSettings:
        scene = api.SceneInput.of("cornell_box.xml", {"cornell_box.xml": xml},
                                  {"resx": str(res), "resy": str(res)}, "cornell")
        start = api.Values([0.5, 0.5, 0.5]) if initial else None
        return api.JobSettings(
            scene, [api.ReferenceInput(0, ref, "ref.exr")],
            [api.ParameterSetting(k, 0.1, 0.0, 1.0, start) for k in (RED, GREEN)],
            iterations=20, schedule="constant", **{"spp": 4, **kw})

    return engine, settings


def _run(engine, name: str, settings, n: int = 4, release: bool = True, end: bool = False
         ) -> list[float]:
    """``n`` iterations; with ``end``, then the job's end as a daemon runs it (its result
    images, its results and standard errors)."""
    engine.start(name, settings, None)
    losses = [engine.step(name, 1).records[0].loss for _ in range(n)]
    if end:
        engine.result_images(name, 0)
        engine.finish(name, [], False, False)
    if release:
        engine.release(name)
    return losses


@contextlib.contextmanager
def _launched():
    """The JIT kernels launched inside, filled in on leaving (Dr.Jit's kernel history, on
    only for that while)."""
    import drjit as dr
    kernels: list[dict] = []
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()  # empties it
        yield kernels
        kernels += [k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)


def test_a_job_run_again_takes_the_kept_scene_compiles_nothing_and_has_the_same_losses(make):
    import drjit as dr
    engine, settings = make
    first = _run(engine, "a", settings())
    kept = engine.kept.kept
    assert kept is not None
    with _launched() as kernels:
        engine.start("b", settings(), None)
        assert engine.runs["b"].scene is kept  # the very scene, not a new load
        again = [engine.step("b", 1).records[0].loss for _ in range(4)]
    # A frozen job records its iteration anew: in a fresh process its recording's kernels
    # hit the cache too, but after other jobs' recordings in the same process they may not
    # (seen after tests/test_frozen.py). The scene's own kernels must never compile again.
    compiled = [k for k in kernels if not k["cache_hit"]
                and k["recording_mode"] != dr.KernelRecordingMode.Recorded]
    engine.release("b")
    assert compiled == []
    np.testing.assert_allclose(again, first, rtol=1e-6)


def test_what_a_job_changed_in_the_scene_is_put_back(make):
    """A job starting from the scene's own values runs as alone after one that moved them
    and resized the film."""
    engine, settings = make
    scene_values = settings(initial=False, seed=3)
    alone = _run(engine, "alone", scene_values)
    _run(engine, "mover", settings())  # starts at grey, moves both walls
    params = mi.traverse(engine.kept.kept.scene)
    assert list(params["camera.film.size"]) == [32, 32]  # as loaded; the job's was 64x32
    assert np.allclose(np.array(params[RED]).ravel(), [0.570068, 0.0430135, 0.0443706])
    np.testing.assert_allclose(_run(engine, "after", scene_values), alone, rtol=1e-6)


def test_two_jobs_on_one_scene_at_once_have_their_own_scenes_and_trajectories(make):
    engine, settings = make
    a_alone = _run(engine, "a", settings())
    b_alone = _run(engine, "b", settings(initial=False, seed=7))
    engine.start("a2", settings(), None)
    engine.start("b2", settings(initial=False, seed=7), None)
    assert engine.runs["a2"].scene.scene is not engine.runs["b2"].scene.scene
    a, b = [], []
    for _ in range(4):  # in turn, as time slices would
        a.append(engine.step("a2", 1).records[0].loss)
        b.append(engine.step("b2", 1).records[0].loss)
    engine.release("a2")
    engine.release("b2")
    np.testing.assert_allclose(a, a_alone, rtol=1e-6)
    np.testing.assert_allclose(b, b_alone, rtol=1e-6)


def test_a_job_on_another_scene_drops_the_kept_one(make):
    engine, settings = make
    _run(engine, "a", settings(32))
    engine.start("other", settings(40), None)
    assert engine.kept.kept is None  # none idle beside the job's own scene
    engine.release("other")
    assert engine.kept.kept.key[0] == settings(40).scene.key


def test_a_texture_job_again_finds_the_texture_as_loaded(service, tmp_path):
    """The next job on a scene whose texture a job optimized (through coarse-to-fine levels)
    starts from the texture as loaded, and runs as the first did."""
    from scenes import exr, textured_quad
    texture = "quad.bsdf.reflectance.data"
    y, x = np.mgrid[0:64, 0:64] / 63.0
    pixels = np.stack([0.2 + 0.6 * x, 0.2 + 0.6 * y, np.full_like(x, 0.4)], -1)
    files = {"scene.xml": textured_quad(24, filename="textures/albedo.exr").encode(),
             "textures/albedo.exr": exr(pixels)}
    for path, data in files.items():
        (tmp_path / "bundle" / path).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / "bundle" / path).write_bytes(data)
    image = mi.render(mi.load_file(str(tmp_path / "bundle" / "scene.xml")), spp=16, seed=5)
    mi.Bitmap(image).write(str(tmp_path / "ref.exr"))
    files["ref.exr"] = (tmp_path / "ref.exr").read_bytes()
    blobs = {hashlib.sha256(d).hexdigest(): d for d in files.values()}
    sha = {p: hashlib.sha256(d).hexdigest() for p, d in files.items()}
    scene = api.SceneInput.of("scene.xml", {p: sha[p] for p in ("scene.xml",
                              "textures/albedo.exr")}, {}, "quad")
    settings = api.JobSettings(
        scene, [api.ReferenceInput(0, sha["ref.exr"], "ref.exr")],
        [api.ParameterSetting(texture, 0.05, 0.0, 1.0, api.Values([0.5] * 64 * 64 * 3))],
        iterations=8, spp=4, schedule="constant")
    engine = service.MitsubaEngine(blobs.__getitem__, tmp_path / "cache")
    first = _run(engine, "a", settings, n=6)  # through the coarse levels to the full one
    params = mi.traverse(engine.kept.kept.scene)
    np.testing.assert_allclose(np.array(params[texture]), pixels, atol=1e-6)
    np.testing.assert_allclose(_run(engine, "b", settings, n=6), first, rtol=1e-6)


def test_on_a_daemon_a_job_again_and_two_jobs_in_turn_have_their_losses_alone(tmp_path):
    """One worker on one thread (its sums in one order), slices of 0.2 s: the same job twice
    in a row, then it and another job on the same scene taking turns (each evicted and
    loaded again from its checkpoint), all with the losses of each job alone."""
    from matopt_api.v1 import matopt_pb2 as pb

    from conftest import Daemon, Stubs, wait_iteration, wait_state
    from test_faults import cornell_job

    daemon = Daemon(tmp_path / "data", None, "--workers", "1", "--server-cores", "1",
                    "--slice", "0.2").start()
    stubs = Stubs(daemon.address)
    try:
        def losses(job: pb.Job) -> list[float]:
            wait_state(stubs, job.name, (pb.JOB_STATE_SUCCEEDED,), timeout=300)
            return [r.loss for r in stubs.jobs.GetJobHistory(
                pb.GetJobHistoryRequest(name=job.name)).iterations]

        first = cornell_job(stubs, 60, seed=7)
        alone = losses(first)
        other = cornell_job(stubs, 60, seed=9)  # the same scene's content, another seed
        other_alone = losses(other)
        again = stubs.jobs.CreateJob(pb.CreateJobRequest(spec=first.spec))
        np.testing.assert_allclose(losses(again), alone, rtol=1e-6)
        a = stubs.jobs.CreateJob(pb.CreateJobRequest(spec=first.spec))
        b = stubs.jobs.CreateJob(pb.CreateJobRequest(spec=other.spec))
        wait_iteration(stubs, b.name, 1)
        assert stubs.jobs.GetJob(pb.GetJobRequest(name=a.name)).iteration < 60  # in turn
        np.testing.assert_allclose(losses(a), alone, rtol=1e-6)
        np.testing.assert_allclose(losses(b), other_alone, rtol=1e-6)
        assert len(alone) == len(other_alone) == 60
    finally:
        stubs.close()
        daemon.stop()


def test_a_frozen_job_again_replays_the_kept_scenes_recording_with_the_same_losses(make):
    """The kept scene keeps the frozen iteration's recording and the integrator it was made
    with: later jobs of the same structure trace nothing at their iteration 0 (their notes and
    status say so) and follow the first job's losses, and their result images replay the
    first job's recording of them. Each job runs to its end as on a daemon: its standard
    errors' renders leave the scene's films and constants otherwise than an iteration does
    (which made every later job record again). Each job's reference also resizes the film,
    which the kept scene puts back, and Dr.Jit now and then lays out a film just resized
    otherwise and records once more: of four later jobs at least three replay, and none
    records more than once."""
    import gc

    import drjit as dr
    gc.collect()  # other tests' scenes, freed in between, would change what a recording
    # traverses (each live instance of a kind the render dispatches over)
    engine, settings = make
    first = _run(engine, "a", settings(), end=True)
    replayed = images_replayed = 0
    for name in ("b", "c", "d", "e"):
        engine.start(name, settings(), None)
        opt = engine.runs[name].opt
        again = [engine.step(name, 1).records[0].loss for _ in range(4)]
        frozen = next(s for s in opt.status() if s.name == "frozen")
        assert opt.group.taken and opt.group.recordings <= 1
        assert "recording from a job before is taken over" in frozen.why
        if opt.group.recordings == 0:
            replayed += 1
            assert opt.said == ["frozen: iteration 0 replayed the recording a job before made "
                                "on this scene: nothing traced or recorded"]
        before = opt.group.images.n_recordings  # the shelf's, which job "a" recorded in
        with _launched() as kernels:
            engine.result_images(name, 0)
        launched = [k["recording_mode"] for k in kernels]
        images_replayed += (opt.group.images.n_recordings == before
                            and dr.KernelRecordingMode.Replayed in launched
                            and dr.KernelRecordingMode.Recorded not in launched)
        engine.finish(name, [], False, False)
        engine.release(name)
        np.testing.assert_allclose(again, first, rtol=1e-6)
    assert replayed >= 3
    assert images_replayed >= 3  # the result images at 64 spp: replayed, nothing traced


def test_result_images_replayed_are_the_images_an_unfrozen_job_renders(make):
    """A job's result images come from the recording kept with the scene where its
    iterations are frozen: the same pixels as rendered unfrozen (frozen=off) at the same
    values and samples."""
    engine, settings = make
    images = {}
    for name, choices in (("frozen", {}), ("unfrozen", {"frozen": "off"}),
                          ("again", {})):
        _run(engine, name, settings(seed=5, choices=choices), release=False)
        renders = engine.runs[name].opt.renders
        assert (renders.frozen is None) == (name == "unfrozen")
        images[name] = renders.render({RED: np.array([0.3, 0.6, 0.2])}, 0, 64)
        engine.release(name)
    assert images["frozen"].shape == (32, 64, 3) and images["frozen"].mean() > 0.05
    np.testing.assert_allclose(images["frozen"], images["unfrozen"], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(images["again"], images["frozen"], rtol=1e-5, atol=1e-6)


def test_a_job_of_another_structure_on_the_kept_scene_records_anew_and_runs_as_alone(make):
    """A recording is replayed only for its own structure: a job at a spp that no job on the
    kept scene ran records anew (its notes say why) and follows the losses it has on a new
    load."""
    engine, settings = make
    alone = _run(engine, "spp8", settings(spp=8))
    engine.kept.drop()  # the next job loads the scene anew: nothing of spp 8 kept
    _run(engine, "a", settings())  # leaves its spp-4 recording on the kept scene
    engine.start("spp8-again", settings(spp=8), None)
    opt = engine.runs["spp8-again"].opt
    again = [engine.step("spp8-again", 1).records[0].loss for _ in range(4)]
    assert opt.said[0] == "frozen: iteration 0 recorded again (spp 4 -> 8)"
    engine.release("spp8-again")
    np.testing.assert_allclose(again, alone, rtol=1e-6)


def test_jobs_of_two_structures_in_turn_on_the_kept_scene_replay_their_own_recordings(
        make, monkeypatch):
    """Users' jobs at two spp taking turns on one scene: each structure's recordings stay
    on the kept scene, so after the first job of each, the jobs replay their own (their
    notes say so) and follow the losses they have alone. Only the last KEPT_STRUCTURES
    structures are kept: a third spp drops the oldest, which then records again. The first
    turn of each spp may record once more (its recording was made on a scene just loaded,
    laid out otherwise), as may a film just resized (see the test above): of the three
    turns after those, at least two replay with nothing recorded."""
    import gc

    from matoptd.engine import frozen
    gc.collect()  # other tests' scenes, freed in between, change what a recording traverses
    monkeypatch.setattr(frozen, "KEPT_STRUCTURES", 2)
    engine, settings = make
    alone = {spp: _run(engine, f"alone{spp}", settings(spp=spp)) for spp in (4, 8)}
    replayed = 0
    for turn, spp in enumerate((4, 8, 4, 8, 4)):
        name = f"turn{turn}"
        engine.start(name, settings(spp=spp), None)
        opt = engine.runs[name].opt
        losses = [engine.step(name, 1).records[0].loss for _ in range(4)]
        engine.release(name)
        np.testing.assert_allclose(losses, alone[spp], rtol=1e-6)
        # the last job's recording is of the other spp: each turn changes the structure
        other = 12 - spp
        assert opt.said[0].startswith("frozen: iteration 0 replays its structure's recording"
                                      f" (spp {other} -> {spp})"), opt.said
        assert opt.group.recordings <= 1
        replayed += turn >= 2 and opt.group.recordings == 0
    assert replayed >= 2
    _run(engine, "spp2", settings(spp=2))  # a third structure: spp 8's are the oldest
    engine.start("spp8-dropped", settings(spp=8), None)
    opt = engine.runs["spp8-dropped"].opt
    engine.step("spp8-dropped", 1)
    engine.release("spp8-dropped")
    assert opt.said[0] == "frozen: iteration 0 recorded again (spp 2 -> 8)"
    assert sorted(spp for spp, _, _ in engine.kept.kept.shelf["frozen"]) == [2, 8]


def test_the_next_job_against_the_same_reference_reads_it_once(make, monkeypatch):
    """The kept scene holds the last job's reference images as read: a job against the same
    file does not decode it again, one against another file does."""
    from matoptd.engine import images
    engine, settings = make
    first = _run(engine, "a", settings())
    read = []
    load = images.load_reference
    monkeypatch.setattr(images, "load_reference", lambda r, blob: read.append(r.name)
                        or load(r, blob))
    assert _run(engine, "b", settings()) == pytest.approx(first, rel=1e-6)
    assert read == []
    other = settings()
    other.references[0] = api.ReferenceInput(0, other.references[0].sha256, "again.exr")
    _run(engine, "c", other)
    assert read == ["again.exr"]


def test_a_job_whose_last_iteration_was_its_best_renders_that_result_once(make):
    """Results render at 64 spp or more, several times an iteration's cost: a job whose best
    iteration is its last (one iteration here) renders it once for both results, the same
    image, beside its initial render."""
    engine, settings = make
    engine.start("once", settings(), None)
    engine.step("once", 1)
    renders = engine.runs["once"].opt.renders
    made = []
    render = renders.render
    renders.render = lambda *a, **kw: made.append(a[0]) or render(*a, **kw)
    try:
        images = engine.result_images("once", 0)
    finally:
        renders.render = render
        engine.release("once")
    assert len(made) == 2  # initial, and iteration 0 for best and last alike
    best = {i.role: i for i in images["best"]}
    last = {i.role: i for i in images["last"]}
    assert best["optimized"].exr == last["optimized"].exr
    assert best["initial"].exr == last["initial"].exr


def _paused(engine, settings, n: int) -> bytes:
    """The checkpoint of a job paused after ``n`` iterations (its run released)."""
    engine.start("paused", settings, None)
    for _ in range(n):
        engine.step("paused", 1)
    checkpoint = engine.checkpoint("paused")
    engine.release("paused")
    return checkpoint


def test_a_paused_jobs_estimate_in_pieces_goes_on_after_its_run_is_lost(make):
    """A paused job's standard errors on request come in pieces, each a call on the worker
    that holds the estimate's run; a worker restarted between two pieces holds it no more,
    and the next piece loads it again from the checkpoint and finishes: the user still gets
    every standard error. The last piece lets the run go."""
    engine, settings = make
    checkpoint = _paused(engine, settings(), 20)

    def ask(run: str, lose_after: int = -1):
        pieces = 0
        while True:
            out = engine.estimate(run, settings(), checkpoint, "last", 0.01)
            pieces += 1
            if out is not None:
                return out, pieces
            if pieces == lose_after:
                engine.release(run)  # what a restart leaves: no run of that name

    whole, pieces = ask("a#estimate-1")
    assert pieces > 2 and "a#estimate-1" not in engine.runs
    again, _ = ask("a#estimate-2", lose_after=1)
    assert "a#estimate-2" not in engine.runs
    for key in (RED, GREEN):
        e, f = whole.errors[key], again.errors[key]
        assert len(f.reading) == 3 and f.reading == e.reading, (e, f)
        assert "not_determined" not in f.reading and np.all(np.isfinite(f.error)), f
        # as uninterrupted, up to J's noise (the spp its passes get follows their time)
        assert np.all((f.error > e.error / 3) & (f.error < 3 * e.error)), (e.error, f.error)


def test_a_later_piece_without_the_checkpoint_says_when_its_run_is_gone(make):
    """Pieces after the first leave out the checkpoint; one that finds its run gone (the
    worker restarted) says so by name, and the daemon sends the checkpoint again."""
    from matoptd import engine_api as api
    engine, settings = make
    checkpoint = _paused(engine, settings(), 5)
    assert engine.estimate("b#e", settings(), checkpoint, "last", 0.01) is None
    engine.estimate("b#e", None, None, "last", 0.01)  # goes on without it (or ends)
    engine.release("b#e")
    with pytest.raises(api.EngineError, match="'b#e' is not loaded on this worker"):
        engine.estimate("b#e", None, None, "last", 0.01)

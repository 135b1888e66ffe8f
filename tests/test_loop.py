"""The optimization loop in-process, on a tiny Cornell box: the hook contract (order, what a
choice sees and returns), a choice's state across a checkpoint, declared conflicts, and the
checkpoint codec. No daemon: the loop and its choices are plain objects here."""

from __future__ import annotations

import io

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba")

from matoptd import settings as api  # noqa: E402

RED = "red.reflectance.value"
GREEN = "green.reflectance.value"


@pytest.fixture(scope="module")
def engine():
    mi.set_variant("llvm_ad_rgb")
    from matoptd.engine import checkpoint, choices, optimize
    return optimize, choices, checkpoint


def _scene():
    scene = mi.cornell_box()
    scene["sensor"]["film"]["width"] = scene["sensor"]["film"]["height"] = 16
    scene["integrator"]["max_depth"] = 3
    return mi.load_dict(scene)


def _settings(iterations: int = 6, **choices: str) -> api.JobSettings:
    return api.JobSettings(api.SceneInput("k", "s.xml", {}, {}, "s.xml"), [],
                           [api.ParameterSetting(RED, 0.05, 0.0, 1.0),
                            api.ParameterSetting(GREEN, 0.05, 0.0, 1.0)],
                           iterations=iterations, spp=4, choices=choices)


def _references(optimize, scene) -> dict:
    image = mi.render(scene, spp=16, seed=99)
    return {0: optimize.Reference(mi.TensorXf(np.asarray(image)[..., :3]), None, "ref")}


def _fakes(choices_module, calls: list[str], HOLD: str | None = None):
    """Two fake choices: one holds GREEN's step (``HOLD``: HOLD unless given) for its first
    two iterations and counts (its state), one scales RED's rate and adds nothing else; both
    log their hooks."""
    Choice, HOLD = choices_module.Choice, HOLD or choices_module.HOLD

    class Holder(Choice):
        name = "holder"
        switchable = False

        def select(self, ctx, records):
            return [GREEN]

        def setup(self, ctx, records, state):
            self.applies, self.why = True, "holds green twice"
            self.count = int(state["count"][0]) if state else 0
            self.seen = sorted(records)
            calls.append("holder.setup")

        def before_render(self, ctx):
            calls.append(f"holder.before_render {ctx.iteration}")
            return {}

        def on_gradient(self, ctx):
            calls.append(f"holder.on_gradient {ctx.iteration}")
            self.count += 1
            return {GREEN: HOLD} if ctx.iteration < 2 else {}

        def state(self):
            return {"count": np.array([self.count])}

    class Halver(Choice):
        name = "halver"
        switchable = False
        after = ("holder",)

        def select(self, ctx, records):
            return [RED]

        def setup(self, ctx, records, state):
            self.applies = True
            calls.append("halver.setup")

        def rate(self, record, rate):
            return rate / 2

        def on_gradient(self, ctx):
            calls.append(f"halver.on_gradient {ctx.iteration} held={sorted(ctx.held)}")
            return {}

    return Holder, Halver


def test_hooks_run_in_order_see_their_own_records_and_their_returns_apply(engine):
    optimize, choices, _ = engine
    calls: list[str] = []
    Holder, Halver = _fakes(choices, calls)
    scene = _scene()
    settings = _settings()
    holder, halver = Holder(settings), Halver(settings)
    loop = optimize.Optimization(scene, settings, _references(optimize, scene),
                                 [holder, halver])
    start = loop.records[GREEN].start.copy()
    assert holder.seen == [GREEN] and calls == ["holder.setup", "halver.setup"]
    for _ in range(3):
        loop.step()
    assert calls[2:6] == ["holder.before_render 0", "holder.on_gradient 0",
                          f"halver.on_gradient 0 held=['{GREEN}']", "holder.before_render 1"]
    # The held steps moved nothing and are recorded as held; the third one moved green.
    assert loop.records[GREEN].held == [0, 1]
    np.testing.assert_allclose(loop.progress.last.values[GREEN], start, atol=0)
    loop.step()
    assert np.abs(loop.progress.last.values[GREEN] - start).max() > 0
    # The rate hook's share: red steps at half its base rate (before the schedule's share).
    assert loop.records[RED].step_rate == pytest.approx(0.025)
    assert loop.records[GREEN].step_rate == pytest.approx(0.05)


def test_a_step_after_a_hold_is_adams_first_step_at_the_rate(engine):
    """Adam's first step moves each component by exactly its rate (m / sqrt(v) debiased is
    g / |g|); held iterations are no steps, so green's first after two held ones is that too
    (counted, it would be debiased as a third step: 0.1 / sqrt(0.001) * sqrt(1 - 0.999^3) /
    (1 - 0.9^3) = 0.639 of the rate)."""
    optimize, choices, _ = engine
    Holder, Halver = _fakes(choices, [])
    scene = _scene()
    settings = _settings()
    loop = optimize.Optimization(scene, settings, _references(optimize, scene),
                                 [Holder(settings), Halver(settings)])
    start = loop.records[GREEN].start.copy()
    for _ in range(3):
        loop.step()  # iterations 0 and 1 held, 2 steps green
    rate = loop.rate(GREEN)  # iteration 2's: the base rate times the schedule's share
    loop.step()
    moved = np.abs(loop.progress.last.values[GREEN] - start)
    np.testing.assert_allclose(moved, rate, rtol=1e-3)


def _eight_iterations(engine):
    """A loop of 8 iterations with the fake choices (green held at iterations 0 and 1)."""
    optimize, choices, _ = engine
    Holder, Halver = _fakes(choices, [])
    scene = _scene()
    settings = _settings(iterations=8)
    return optimize, settings, optimize.Optimization(
        scene, settings, _references(optimize, scene), [Holder(settings), Halver(settings)])


def test_a_variable_released_mid_job_steps_on_a_schedule_that_starts_at_its_release(engine):
    """The cosine's share is 1 at a variable's schedule_begin and a tenth at the job's last
    step; the others keep the job's own."""
    optimize, settings, loop = _eight_iterations(engine)
    for _ in range(2):
        loop.step()
    loop.records[GREEN].schedule_begin = 2
    shares = []
    for i in range(2, 7):  # the steps taken (the last iteration takes none)
        loop.step()
        shares.append((loop.rate(GREEN) / loop.records[GREEN].step_rate,
                       loop.rate(RED) / loop.records[RED].step_rate))
    green, red = zip(*shares)
    assert green[0] == pytest.approx(1.0) and red[0] == pytest.approx(0.1 + 0.45 * 1.62349)
    assert green == pytest.approx([optimize.schedule_factor(settings, i, 2) for i in range(2, 7)])
    assert red == pytest.approx([optimize.schedule_factor(settings, i) for i in range(2, 7)])
    assert optimize.schedule_factor(settings, 7, 2) == pytest.approx(0.1)
    assert all(g > r for g, r in zip(green, red))


def test_a_variable_that_does_not_decay_keeps_its_full_rate_to_the_end(engine):
    """A record a choice keeps whole (medium_constant_rate) steps at its step rate at every
    iteration, while the others decay toward a tenth."""
    optimize, settings, loop = _eight_iterations(engine)
    loop.records[GREEN].decays = False
    for _ in range(7):
        loop.step()
        assert loop.rate(GREEN) == pytest.approx(loop.records[GREEN].step_rate)
    decayed = optimize.schedule_factor(settings, loop.ctx.iteration)
    assert decayed < 0.15 and loop.rate(RED) == pytest.approx(decayed * loop.records[RED].step_rate)


def test_a_choice_that_lowers_adams_momentum_sets_it_for_the_jobs_optimizer(engine):
    """A choice's adam_beta_1 (medium_damping's) is the beta_1 of the job's one Adam: after
    its first step each component's first moment is (1 - beta_1) g and its second moment
    (1 - beta_2) g^2, so m^2 / (1 - beta_1)^2 = v / (1 - beta_2) holds at 0.5, not at 0.9."""
    optimize, choices, _ = engine

    class Damper(choices.Choice):
        name = "damper"
        switchable = False

        def select(self, ctx, records):
            return [RED]

        def setup(self, ctx, records, state):
            self.applies, self.adam_beta_1 = True, 0.5

    scene = _scene()
    settings = _settings()
    refs = _references(optimize, scene)
    for made, beta_1 in (([Damper(settings)], 0.5), ([], 0.9)):
        loop = optimize.Optimization(scene, settings, refs, made)
        assert loop.opt.beta_1 == beta_1
        loop.step()
        _, m, v, _ = loop.opt.state[GREEN][3]
        m, v = np.asarray(m), np.asarray(v)
        assert np.all(v > 0)
        np.testing.assert_allclose(m ** 2 / (1 - beta_1) ** 2, v / (1 - 0.999), rtol=1e-3)


def test_a_choices_state_and_the_loop_survive_a_checkpoint(engine):
    optimize, choices, _ = engine
    Holder, Halver = _fakes(choices, [])
    scene = _scene()
    refs = _references(optimize, scene)
    settings = _settings(iterations=8)
    whole = optimize.Optimization(scene, settings, refs, [Holder(settings), Halver(settings)])
    losses = [whole.step().loss for _ in range(8)]

    scene = _scene()
    first = optimize.Optimization(scene, settings, refs, [Holder(settings), Halver(settings)])
    before = [first.step().loss for _ in range(4)]
    saved = first.checkpoint()
    holder = Holder(settings)
    again = optimize.Optimization(_scene(), settings, refs, [holder, Halver(settings)], saved)
    assert holder.count == 4  # its own state, restored through setup
    assert again.progress.iteration == 4 and again.records[GREEN].held == [0, 1]
    after = [again.step().loss for _ in range(4)]
    # The same seeds and the same state: the same trajectory as without the interruption.
    np.testing.assert_allclose(before + after, losses, rtol=1e-4)
    np.testing.assert_allclose(again.progress.last.values[RED],
                               whole.progress.last.values[RED], rtol=1e-4)


def test_two_choices_that_exclude_each_other_are_refused_naming_both(engine):
    optimize, choices, _ = engine

    class Mine(choices.Choice):
        name = "mine"
        switchable = False
        excludes = ("theirs",)

        def select(self, ctx, records):
            return [RED]

    class Theirs(Mine):
        name = "theirs"
        excludes = ()

    scene = _scene()
    settings = _settings()
    with pytest.raises(choices.ConflictError, match="mine and theirs cannot both be on for "
                       f"{RED}"):
        optimize.Optimization(scene, settings, _references(optimize, scene),
                              [Mine(settings), Theirs(settings)])


def test_a_declaration_naming_no_choice_or_out_of_order_is_refused(engine):
    _, choices, _ = engine

    class Early(choices.Choice):
        name = "early"
        after = ("late",)

    class Late(choices.Choice):
        name = "late"

    class Stray(choices.Choice):
        name = "stray"
        yields_to = ("nowhere",)

    with pytest.raises(ValueError, match="early runs after"):
        choices.base.check_declarations((Early, Late))
    with pytest.raises(ValueError, match="yields_to names no choice"):
        choices.base.check_declarations((Stray,))
    choices.base.check_declarations(choices.REGISTRY)  # the real ones hold


def test_the_checkpoint_codec_round_trips_by_name_and_reads_the_positional_layout(engine):
    _, _, codec = engine
    from matoptd.engine.records import Best, Progress
    progress = Progress(7, 1.5, 1, 0, 3, [0.25, 0.5],
                        Best(5, 0.1, {RED: np.array([0.2, 0.3, 0.4], np.float32)},
                             {0: np.array([1.0, 2.0, 3.0], np.float32)}),
                        Best(6, 0.2, {RED: np.array([0.25, 0.3, 0.4], np.float32)}))
    cp = codec.Checkpoint(progress, {RED: codec.VariableState(
        np.arange(3, dtype=np.float32), np.array([7], np.uint32), np.ones(3, np.float32),
        np.full(3, 2.0, np.float32), [1, 2])},
        {"eta_hold": codec.ChoiceState(0.5, 0.1, {"released": np.array([3], np.int64)})})
    back = codec.loads(codec.dumps(cp))
    assert back.progress.iteration == 7 and back.progress.recent == [0.25, 0.5]
    assert back.progress.best.gains[0].tolist() == [1.0, 2.0, 3.0]
    assert back.variables[RED].t.dtype == np.uint32 and back.variables[RED].held == [1, 2]
    assert back.choices["eta_hold"].state["released"].dtype == np.int64

    # The layout before this codec: positional meta, arrays numbered by Adam key.
    buf = io.BytesIO()
    np.savez(buf, keys=np.array([RED, "gain0"]),
             meta=np.array([7, 1.5, 5, 0.1, 1, 0, 3, 6, 0.2]), recent=np.array([0.25, 0.5]),
             value0=np.zeros(3, np.float32), t0=np.array([7], np.uint32),
             m0=np.zeros(3, np.float32), v0=np.zeros(3, np.float32), held0=np.array([1]),
             best0=np.full(3, 0.2, np.float32), best1=np.ones(3, np.float32),
             value1=np.zeros(3, np.float32), t1=np.array([7], np.uint32),
             m1=np.zeros(3, np.float32), v1=np.zeros(3, np.float32),
             **{"cost:eta_hold": np.array([0.5, 0.1]),
                "choice:eta_hold:released": np.array([3])})
    old = codec.loads(buf.getvalue())
    assert old.progress.iteration == 7 and old.progress.best.iteration == 5
    assert list(old.progress.best.values) == [RED] and list(old.progress.best.gains) == [0]
    assert old.progress.last.iteration == -1  # none kept
    assert old.variables[RED].held == [1] and old.choices["eta_hold"].seconds == 0.5
    with pytest.raises(codec.CheckpointError, match="not a checkpoint"):
        codec.loads(b"not a zip")

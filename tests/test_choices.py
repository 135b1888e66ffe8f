"""The engine's named choices: which are on for a job's settings, when eta is released from its
hold (pure logic), and, through a real daemon, what a job's status says of its choices, turning
one off, and bad names or values refused."""

from __future__ import annotations

import re
import types

import grpc
import numpy as np
import pytest

from matopt_api.v1 import matopt_pb2 as pb
from matoptd import settings as api
from matoptd.engine.choices import REGISTRY, assign_keys
from matoptd.engine.choices.depth import LADDER, larger_cut, least_depth
from matoptd.engine.choices.eta_hold import EtaHold
from matoptd.engine.choices.linear_extinction import LinearExtinction
from matoptd.engine.choices.log_space import LogSpace
from matoptd.engine.choices.medium_constant_rate import MediumConstantRate
from matoptd.engine.choices.medium_damping import BETA_1, MediumDamping
from matoptd.engine.choices.roughness_constant_rate import RoughnessConstantRate
from matoptd.engine.choices.slow_interface_width import SlowInterfaceWidth
from matoptd.engine.choices.settling import SETTLED, WINDOW, Path
from matoptd.engine.records import ParamRecord

import thesis_scenes as ts
from conftest import Daemon, Stubs, wait_iteration, wait_state
from scenes import PRINCIPLED, create_scene
from stiff import glass


def _settings(**choices: str) -> api.JobSettings:
    return api.JobSettings(api.SceneInput("k", "s.xml", {}, {}, "s.xml"), [],
                           [api.ParameterSetting("obj.eta", 0.01, 1.001, 4.0)],
                           choices=choices)


def test_every_choice_is_on_unless_turned_off_by_name_or_all():
    assert [c.name for c in REGISTRY if not _settings().choice_on(c.name)] == [
        "slow_interface_width", "medium_damping", "roughness_constant_rate",
        "gauss_newton"]  # the candidates
    assert _settings(gauss_newton="on").choice_on("gauss_newton")
    assert _settings(all="on").choice_on("roughness_constant_rate")
    off = _settings(eta_differences="off")
    assert not off.choice_on("eta_differences") and off.choice_on("log_space")
    plain = _settings(all="off", depth="on")
    assert plain.choice_on("depth") and not plain.choice_on("log_space")
    # Choices a setting asks for are not switched by name: they follow that setting.
    asked = [c.name for c in REGISTRY if not c.switchable]
    assert sorted(asked) == ["exposure_gains", "smoothness"]
    assert all(c(_settings(all="off")).on for c in REGISTRY if not c.switchable)


SIGMA_T, GRID = "medium.sigma_t.value.value", "cloud.sigma_t.data"


def _records(settings: api.JobSettings, starts: dict[str, np.ndarray]) -> dict:
    """A record per parameter, as the loop makes them (scene values at the starts)."""
    return {p.key: ParamRecord(p.key, "scalar", p.lo, p.hi, p.learning_rate, starts[p.key],
                               starts[p.key]) for p in settings.parameters}


def _set_up(choices: list, settings: api.JobSettings, records: dict, state=None) -> None:
    ctx = types.SimpleNamespace(settings=settings)
    assign_keys(ctx, choices, records)
    for c in choices:
        c.setup(ctx, {k: records[k] for k in c.keys}, state)


def _extinctions(**choices: str):
    """A homogeneous sigma_t started at 2 (rate 0.03) and a grid's sigma_t."""
    inf = float("inf")
    settings = api.JobSettings(api.SceneInput("k", "s.xml", {}, {}, "s.xml"), [],
                               [api.ParameterSetting(SIGMA_T, 0.03, 0.0, inf),
                                api.ParameterSetting(GRID, 0.2, 0.0, inf)], choices=choices)
    return settings, _records(settings, {SIGMA_T: np.array([2.0]), GRID: np.full(8, 2.0)})


def test_a_homogeneous_extinction_steps_linearly_at_a_share_of_its_value_or_start():
    settings, records = _extinctions()
    linear, logs = LinearExtinction(settings), LogSpace(settings)
    _set_up([linear, logs], settings, records)
    assert logs.keys == [GRID]  # a grid's texels span decades: log space still
    record = records[SIGMA_T]
    assert linear.rate(record, 0.03) == pytest.approx(0.03 * 2.0)
    # Below its start, the start's share (absolute steps); above it, the value's (relative).
    for value, rate in ((0.4, 0.06), (0.0, 0.06), (50.0, 1.5)):
        record.current = np.array([value])
        assert linear.rate(record, 0.03) == pytest.approx(rate)
    assert linear.keys == [SIGMA_T]
    assert "0.06 per step at full rate below the start" in linear.notes()[0]

    # Turned off, log space takes sigma_t back (it yields only to a linear_extinction on).
    settings, records = _extinctions(linear_extinction="off")
    linear, logs = LinearExtinction(settings), LogSpace(settings)
    _set_up([linear, logs], settings, records)
    assert logs.keys == [SIGMA_T, GRID] and logs.rates[SIGMA_T] == 0.03


ALPHA, ETA, ALBEDO = "glass.alpha.value", "glass.eta", "medium.albedo.value.value"


def _interface(alpha_rate: float | None = None, medium: bool = True, **choices: str):
    """A rough dielectric's alpha and eta around a homogeneous medium (its albedo, sigma_t) and
    a grid's sigma_t; alpha at the listed width rate unless ``alpha_rate`` is given."""
    inf = float("inf")
    params = [api.ParameterSetting(ALPHA, alpha_rate or 0.2, 0.0, 1.0),
              api.ParameterSetting(ETA, 0.01, 1.001, 4.0),
              api.ParameterSetting(GRID, 0.2, 0.0, inf)]
    if medium:
        params += [api.ParameterSetting(ALBEDO, 0.03, 0.0, 1.0),
                   api.ParameterSetting(SIGMA_T, 0.03, 0.0, inf)]
    settings = api.JobSettings(api.SceneInput("k", "s.xml", {}, {}, "s.xml"), [], params,
                               choices=choices)
    starts = {ALPHA: np.array([0.98]), ETA: np.array([1.55]), GRID: np.full(8, 2.0),
              ALBEDO: np.full(3, 0.01), SIGMA_T: np.array([0.99])}
    records = _records(settings, starts)
    records[ALPHA].rate_given = alpha_rate is not None
    for key in (ALBEDO, SIGMA_T) if medium else ():
        records[key].rate_given = False  # the listed rates
    records[GRID].kind = "volume_grid"
    return settings, records


ROUGHNESS, BASE = "bunny.roughness.value", "bunny.base_color.value"


def _principled(roughness_rate: float | None = None, eta: bool = True, **choices: str):
    """A principled BSDF's roughness, base colour and (``eta``) eta; the roughness at the
    listed width rate unless ``roughness_rate`` is given."""
    params = [api.ParameterSetting(ROUGHNESS, roughness_rate or 0.2, 0.0, 1.0),
              api.ParameterSetting(BASE, 0.03, 0.0, 1.0)]
    if eta:
        params.append(api.ParameterSetting("bunny.eta", 0.01, 1.001, 4.0))
    settings = api.JobSettings(api.SceneInput("k", "s.xml", {}, {}, "s.xml"), [], params,
                               choices=choices)
    records = _records(settings, {ROUGHNESS: np.array([0.5]), BASE: np.full(3, 0.5),
                                  "bunny.eta": np.array([1.55])})
    records[ROUGHNESS].rate_given = roughness_rate is not None
    return settings, records


def test_a_principled_roughness_beside_eta_keeps_its_full_rate_only_when_named():
    settings, records = _principled(roughness_constant_rate="on")
    choice = RoughnessConstantRate(settings)
    _set_up([choice], settings, records)
    assert choice.on and choice.keys == [ROUGHNESS]
    assert [k for k, r in records.items() if not r.decays] == [ROUGHNESS]
    # By default it is off, says what it would do, and the roughness decays.
    settings, records = _principled()
    choice = RoughnessConstantRate(settings)
    _set_up([choice], settings, records)
    assert not choice.on and choice.applies and "decays with the schedule" in choice.why
    assert all(r.decays for r in records.values())
    # Without an eta beside it, with a rate the job gave, or a rough dielectric's alpha (where
    # Table 4 did worse kept whole), it has nothing to keep.
    for settings, records in (_principled(eta=False, roughness_constant_rate="on"),
                              _principled(0.05, roughness_constant_rate="on"),
                              _interface(roughness_constant_rate="on")):
        choice = RoughnessConstantRate(settings)
        _set_up([choice], settings, records)
        assert not choice.applies and all(r.decays for r in records.values())


def test_a_medias_albedo_and_extinction_keep_their_full_rate_and_nothing_else_does():
    settings, records = _interface()  # on by default
    choice = MediumConstantRate(settings)
    _set_up([choice], settings, records)
    assert choice.on and sorted(choice.keys) == [ALBEDO, SIGMA_T]  # not the grid
    assert [k for k, r in records.items() if not r.decays] == [ALBEDO, SIGMA_T]
    # Off, it says what it would do and leaves every variable to the schedule.
    settings, records = _interface(medium_constant_rate="off")
    choice = MediumConstantRate(settings)
    _set_up([choice], settings, records)
    assert not choice.on and choice.applies and "decay with the schedule" in choice.why
    assert all(r.decays for r in records.values())
    # The valley is the pair's: sigma_t alone, or a pair with a rate the job gave, decays.
    alone = _interface()
    del alone[1][ALBEDO]
    given = _interface()
    given[1][SIGMA_T].rate_given = True
    for settings, records in (alone, given):
        choice = MediumConstantRate(settings)
        _set_up([choice], settings, records)
        assert not choice.applies and all(r.decays for r in records.values())


def test_a_medias_pair_lowers_adams_momentum_only_when_named():
    """medium_damping, a candidate: named, a job with a medium's albedo and sigma_t takes
    Adam's beta_1 at 0.5; unnamed, it says what it would do and leaves Adam's 0.9."""
    settings, records = _interface(medium_damping="on")
    choice, whole = MediumDamping(settings), MediumConstantRate(settings)
    _set_up([whole, choice], settings, records)
    assert choice.on and sorted(choice.keys) == [ALBEDO, SIGMA_T]
    assert choice.adam_beta_1 == BETA_1 == 0.5 and "beta_1 0.5" in choice.why
    # It takes the pair from medium_constant_rate: at the lower momentum the pair decays.
    assert whole.keys == [] and all(r.decays for r in records.values())
    assert records[ALBEDO].schedule_begin == 0 and "on the schedule" in choice.why
    settings, records = _interface()
    choice = MediumDamping(settings)
    _set_up([choice], settings, records)
    assert not choice.on and choice.applies and choice.adam_beta_1 is None
    assert "beta_1 0.9" in choice.why
    # The swing is the pair's: sigma_t alone, or a pair with a rate the job gave, is not taken.
    alone = _interface(medium_damping="on")
    del alone[1][ALBEDO]
    given = _interface(medium_damping="on")
    given[1][SIGMA_T].rate_given = True
    for settings, records in (alone, given):
        choice = MediumDamping(settings)
        _set_up([choice], settings, records)
        assert not choice.applies and choice.keys == []


class _Climb:
    """What medium_damping's hook reads of the loop: the iteration, theta_i and its rate."""

    def __init__(self, choice):
        self.choice, self.values, self.iteration = choice, {}, -1

    def latent(self, key):
        return self.values[key]

    def rate(self, key):
        return 0.03

    def step(self, values: dict) -> None:
        self.iteration += 1
        self.values = {k: np.asarray(v, float) for k, v in values.items()}
        self.choice.on_gradient(self)


def test_a_damped_medium_keeps_its_full_rate_while_it_climbs_and_decays_once_it_settles():
    """medium_damping=settle: the pair at its full rate while either still moves steadily;
    once both only jitter over a window, the schedule's decay runs from that iteration, and a
    job restored from a checkpoint goes on from it. medium_constant_rate yields the pair."""
    settings, records = _interface(medium_damping="settle")
    choice, whole = MediumDamping(settings), MediumConstantRate(settings)
    _set_up([whole, choice], settings, records)
    assert whole.keys == [] and sorted(choice.keys) == [ALBEDO, SIGMA_T]
    assert [k for k, r in records.items() if not r.decays] == [ALBEDO, SIGMA_T]
    climb = _Climb(choice)
    jitter = lambda i: 0.4 + 0.2 * 0.03 * (-1) ** i  # noqa: E731
    # The albedo settles while sigma_t still climbs: both keep their rate.
    for i in range(3 * WINDOW):
        climb.step({ALBEDO: np.full(3, jitter(i)), SIGMA_T: [0.1 + 0.03 * i]})
    assert not records[ALBEDO].decays and not records[SIGMA_T].decays
    # Both jitter where sigma_t's climb ended: within a window the pair decays, its
    # schedule begun there.
    for i in range(WINDOW + 1):
        climb.step({ALBEDO: np.full(3, jitter(i)), SIGMA_T: [0.97 + 1e-4 * (-1) ** i]})
        if records[SIGMA_T].decays:
            break
    begun = climb.iteration
    assert 3 * WINDOW < begun <= 4 * WINDOW
    assert records[ALBEDO].decays and records[SIGMA_T].schedule_begin == begun
    assert f"settled at iteration {begun}" in choice.why
    settings, records = _interface(medium_damping="settle")
    again = MediumDamping(settings)
    _set_up([again], settings, records, choice.state())
    assert records[ALBEDO].decays and records[ALBEDO].schedule_begin == begun


class _Walk:
    """What ConstantRate's hooks read of the loop: theta_{i-1} of each key and its rate."""

    def __init__(self, choice):
        self.choice, self.values = choice, {}

    def value(self, key):
        return self.values.get(key)

    latent = value

    def rate(self, key):
        return self.choice.rate(None, 0.03)

    def step(self, values: dict) -> float:
        self.values = {k: np.asarray(v, float) for k, v in values.items()}
        self.choice.before_render(self)
        return self.choice.share


def test_a_medium_kept_whole_until_it_settles_steps_at_a_shrinking_share_after():
    """medium_constant_rate=settle: the full rate while the pair descends steadily; each
    window in which both only jitter halves it, down to the schedule's floor (a tenth)."""
    settings, records = _interface(medium_constant_rate="settle")
    choice = MediumConstantRate(settings)
    _set_up([choice], settings, records)
    assert choice.settle and [k for k, r in records.items() if not r.decays] == [ALBEDO, SIGMA_T]
    walk = _Walk(choice)
    # A steady descent (a full step each iteration) keeps the whole rate.
    shares = [walk.step({ALBEDO: np.full(3, 0.01 + 0.03 * i), SIGMA_T: [0.99 - 0.03 * i]})
              for i in range(3 * WINDOW)]
    assert shares[-1] == 1.0 and choice.rate(records[ALBEDO], 0.03) == pytest.approx(0.03)
    # While sigma_t still descends, the albedo's jitter alone does not shrink the pair's rate.
    jitter = lambda i: 0.4 + 0.2 * 0.03 * (-1) ** i  # noqa: E731
    shares = [walk.step({ALBEDO: np.full(3, jitter(i)), SIGMA_T: [2.0 - 0.03 * i]})
              for i in range(2 * WINDOW)]
    assert shares[-1] == 1.0
    # Both jitter: halved after each window of their own, to a tenth and no lower.
    shares = [walk.step({ALBEDO: np.full(3, jitter(i)), SIGMA_T: [0.04 + 1e-4 * (-1) ** i]})
              for i in range(6 * (WINDOW + 1))]
    assert shares[WINDOW - 1] == 1.0 and shares[WINDOW] == 0.5
    assert shares[2 * WINDOW + 1] == 0.25 and shares[-1] == pytest.approx(0.1)
    assert choice.rate(records[SIGMA_T], 0.03) == pytest.approx(0.003)
    assert "(now 0.1)" in choice.why
    # A job restored from a checkpoint goes on at the share it left with.
    settings, records = _interface(medium_constant_rate="settle")
    again = MediumConstantRate(settings)
    _set_up([again], settings, records, choice.state())
    assert again.share == pytest.approx(0.1)
    # Plain "on" keeps the full rate to the end, whatever the path.
    settings, records = _interface()
    whole = MediumConstantRate(settings)
    _set_up([whole], settings, records)
    walk = _Walk(whole)
    for i in range(3 * WINDOW):
        walk.step({ALBEDO: np.full(3, jitter(i)), SIGMA_T: [0.04]})
    assert not whole.settle and whole.rate(records[ALBEDO], 0.03) == 0.03


def test_a_dielectrics_width_around_a_medium_steps_at_half_its_listed_rate():
    settings, records = _interface(slow_interface_width="on")  # off unless named
    choice = SlowInterfaceWidth(settings)
    _set_up([choice], settings, records)
    assert choice.on and choice.applies and choice.keys == [ALPHA]
    assert choice.rate(records[ALPHA], 0.2) == pytest.approx(0.1)
    assert "0.1 in place of 0.2" in choice.notes()[0]
    # By default off, saying that the width steps at its listed rate.
    settings, records = _interface()
    choice = SlowInterfaceWidth(settings)
    _set_up([choice], settings, records)
    assert not choice.on and choice.applies and "at its listed rate" in choice.why
    # A rate the job gave is the job's; without a medium, eta's differences decide eta.
    for settings, records in (_interface(0.3, slow_interface_width="on"),
                              _interface(medium=False, slow_interface_width="on")):
        choice = SlowInterfaceWidth(settings)
        _set_up([choice], settings, records)
        assert not choice.applies and choice.keys == []


def _path(values: list[float], rate: float = 0.1) -> Path:
    path = Path()
    for v in values:
        path.add(np.array([v]), rate)
    return path


def test_a_variable_has_settled_once_it_nets_a_small_share_of_its_steps():
    # A steady descent moves by about its rate each step: not settled.
    assert not _path([0.5 - 0.09 * n for n in range(WINDOW + 1)]).settled()
    # Jitter about the optimum nets a small share of the steps it was allowed: settled.
    jitter = [0.2 + 0.05 * (-1) ** n for n in range(WINDOW + 1)]
    assert _path(jitter).settled()
    # Just past the threshold: a net move of a little more than SETTLED of the allowed steps.
    assert not _path([0.0] * WINDOW + [1.01 * SETTLED * 0.1 * WINDOW]).settled()
    assert _path([0.0] * WINDOW + [0.99 * SETTLED * 0.1 * WINDOW]).settled()
    # Too short a history is never settled; steps not taken (rate 0) allow nothing.
    assert not _path(jitter[:WINDOW]).settled()
    frozen = _path([0.3] * (WINDOW + 1), rate=0.0)
    assert frozen.settled()
    # A checkpoint's arrays give the same path back.
    again = Path.restored(_path(jitter).state("p"), "p")
    assert again.settled() and len(again.values) == WINDOW + 1
    # A swing's far end: six full steps out and four back net a fifth of the allowed steps
    # but span 0.6 of them. The net test takes it for settled, the spread test
    # (medium_damping's) does not; jitter passes both.
    turn = [0.1 * min(n, 12 - n) for n in range(WINDOW + 1)]
    assert _path(turn).settled() and not _path(turn).settled(spread=True)
    assert _path(jitter).settled(spread=True)


def _job(stubs, case: ts.Case, iterations: int, **choices: str) -> pb.Job:
    scene = create_scene(stubs, case.files, case.main)
    ref = stubs.scenes.RenderScene(pb.RenderSceneRequest(name=scene.name, spp=64)).images[0]
    spec = pb.JobSpec(scene=scene.name, iterations=iterations, min_error=0,
                      references=[pb.Reference(blob=ref.exr_blob)],
                      parameters=[pb.ParameterSpec(key=k, initial_value=list(np.ravel(v)))
                                  for k, v in case.start.items()])
    spec.choices.update(choices)
    name = stubs.jobs.CreateJob(pb.CreateJobRequest(spec=spec)).name
    job = wait_state(stubs, name, (pb.JOB_STATE_SUCCEEDED, pb.JOB_STATE_FAILED))
    assert job.state == pb.JOB_STATE_SUCCEEDED, job.error
    return job


def test_the_status_lists_the_choices_in_force_and_one_can_be_turned_off(stubs):
    """Table 2's kind at 16 px: its roughness is stepped in log space and shown at no less
    than the floor, its eta is differenced near the specular limit (and not held: there is no
    medium it could stand in for)."""
    case = ts.table2(res=16)
    job = _job(stubs, case, 8)
    choices = {c.name: c for c in job.choices}
    assert {"log_space", "roughness_floor", "eta_differences"} <= set(choices)
    assert "eta_hold" not in choices
    candidates = ("gauss_newton", "roughness_constant_rate")  # off unless named
    assert all(c.on == (name not in candidates) and c.switchable and c.why
               for name, c in choices.items())
    assert "Adam" in choices["gauss_newton"].why  # off unless named: what it would do instead
    assert "decays with the schedule" in choices["roughness_constant_rate"].why
    assert "relative" in choices["log_space"].why
    # Measured: its hooks' time per iteration (the differences render, the floor only maps).
    assert choices["eta_differences"].seconds_per_iteration >= 0
    assert choices["roughness_floor"].seconds_per_iteration < 0.01
    assert any("its listed rate 0.2 is a relative step" in n for n in job.notes)

    off = _job(stubs, case, 8, eta_differences="off", log_space="off")
    choices = {c.name: c for c in off.choices}
    assert not choices["eta_differences"].on and not choices["log_space"].on
    assert choices["roughness_floor"].on
    assert choices["eta_differences"].seconds_per_iteration == 0
    assert not any("central differences" in n or "relative step" in n for n in off.notes)


@pytest.mark.parametrize("choices, message", [
    ({"eta_diferences": "off"}, "unknown choice 'eta_diferences' (did you mean "
                                "'eta_differences'?)"),
    ({"depth": "maybe"}, "choice 'depth' cannot be 'maybe': give on or off"),
    ({"eta_differences": "half"}, "choice 'eta_differences' cannot be 'half': give on, off, "
                                  "quarter or full, optionally with :ALPHA"),
    ({"eta_differences": "full:2"}, "choice 'eta_differences' cannot be 'full:2': give on, "
                                    "off, quarter or full, optionally with :ALPHA (the width "
                                    "below which they apply, in (0, 1]"),
    ({"medium_constant_rate": "slow"}, "choice 'medium_constant_rate' cannot be 'slow': give "
                                       "on, off or settle"),
    # Its value says how the pair decays, not Adam's beta_1
    ({"medium_damping": "0.7"}, "choice 'medium_damping' cannot be '0.7': give on, off or "
     "settle"),
])
def test_a_bad_choice_is_refused_naming_it(stubs, choices, message):
    case = ts.table2(res=8)
    scene = create_scene(stubs, case.files, case.main)
    ref = stubs.scenes.RenderScene(pb.RenderSceneRequest(name=scene.name, spp=1)).images[0]
    spec = pb.JobSpec(scene=scene.name, references=[pb.Reference(blob=ref.exr_blob)],
                      parameters=[pb.ParameterSpec(key=f"{ts.BSDF}.eta")])
    spec.choices.update(choices)
    with pytest.raises(grpc.RpcError) as err:
        stubs.jobs.CreateJob(pb.CreateJobRequest(spec=spec))
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert message in err.value.details()


def test_eta_waits_while_the_medium_behind_it_still_moves(stubs):
    """Table 4's kind (rough glass around a medium started black): eta stays at its start
    while albedo and sigma_t still climb, and says so; turned off, it moves at once."""
    case = ts.table4(res=16)
    eta = f"{ts.BSDF}.eta"

    def etas(job: pb.Job) -> list[float]:
        history = stubs.jobs.GetJobHistory(pb.GetJobHistoryRequest(name=job.name)).iterations
        return [next(v.value[0] for v in r.parameters if v.key == eta) for r in history]

    held = _job(stubs, case, 24)
    choice = next(c for c in held.choices if c.name == "eta_hold")
    assert choice.on and "albedo" in choice.why and "sigma_t" in choice.why
    # Its homogeneous sigma_t steps linearly, outside log space, and the notes say how.
    choices = {c.name: c for c in held.choices}
    assert choices["linear_extinction"].on and "sigma_t" in choices["linear_extinction"].why
    assert "sigma_t" not in choices["log_space"].why
    assert any("sigma_t" in n and "stepped linearly" in n for n in held.notes)
    # The interface's width at its listed rate (its half rate off unless named); the medium's
    # pair undecayed.
    assert not choices["slow_interface_width"].on
    assert "alpha" in choices["slow_interface_width"].why
    assert not any("0.1 in place of 0.2" in n for n in held.notes)
    assert choices["medium_constant_rate"].on
    assert all(k in choices["medium_constant_rate"].why for k in ("albedo", "sigma_t"))
    # Adam's momentum as Dr.Jit's (its lowering, a candidate, off unless named)
    assert not choices["medium_damping"].on and "beta_1 0.9" in choices["medium_damping"].why
    # No release before WINDOW steps of the others are known.
    assert etas(held)[:WINDOW + 1] == pytest.approx([case.start[eta][0]] * (WINDOW + 1))
    free = etas(_job(stubs, case, 12, eta_hold="off"))
    assert abs(free[-1] - case.start[eta][0]) > 0.02


def _bounces(noise: float, iterations: int):
    """A fake renderer: pixel noise of one render's variance ``noise`` drawn by the seed, and
    light from bounce k of 0.5^k per pixel, so a cut at d changes every pixel by the tail
    sum_{k>d} 0.5^k = 0.5^d. Returns it and the least depth of LADDER the test should take."""
    rng_shape = (4, 5, 3)

    def renders(d: int, seed: int) -> dict[int, np.ndarray]:
        tail = 0.0 if d < 0 else 0.5 ** d
        grain = np.random.default_rng(seed).standard_normal(rng_shape) * np.sqrt(noise)
        return {0: 1.0 - tail + grain}
    # c(d) = 0.25^d against noise / iterations (the sample variance of 60 draws, near it)
    expected = min(d for d in LADDER if 0.25 ** d < 0.5 * noise / iterations)
    return renders, {0: np.ones(rng_shape)}, expected


def test_the_depth_test_takes_the_least_cut_under_the_noise_of_the_jobs_mean():
    """The `depth` choice's test on a renderer whose tail is known: the least depth of the
    ladder whose cut changes the image by less than the job's mean's noise; more noise or
    fewer iterations allow a shallower cut; a bounded depth keeps candidates below it, and
    ``least`` those from it on. The start's cut wins only where it is deeper."""
    renders, ones, expected = _bounces(1e-4, 100)
    depth, change, noise = least_depth(renders, ones, 100, -1)
    assert change < noise and 0.25 ** depth == pytest.approx(change, rel=1e-6)
    assert depth in (expected, LADDER[LADDER.index(expected) + 1])  # noise's own estimate
    assert least_depth(renders, ones, 100, -1, least=48)[0] == 48
    shallow = least_depth(renders, ones, 1, -1)[0]
    assert shallow < depth
    assert least_depth(renders, ones, 100, 8) == (8, 0.0, pytest.approx(noise))  # none passes
    # the scene's values first, then the start from that cut on: the larger one
    calls = []

    def at(value: int):
        return lambda least: calls.append(least) or (value if value < 0 else max(value, least),
                                                      0.0, 1.0)
    assert larger_cut(at(16), at(24), -1)[0] == 24 and calls == [0, 16]
    assert larger_cut(at(16), at(12), -1)[0] == 16
    calls.clear()
    assert larger_cut(at(-1), at(24), -1)[0] == -1 and calls == [0]  # the scene's depth stands


UNBOUNDED = PRINCIPLED.replace(
    '<integrator type="path"><integer name="max_depth" value="6"/></integrator>',
    '<default name="max_depth" value="-1"/>\n'
    '    <integrator type="path"><integer name="max_depth" value="$max_depth"/></integrator>')


def test_an_unbounded_depth_is_cut_where_the_image_stops_changing_unless_the_user_sets_it(
        stubs):
    """A translucent principled ball (spec_trans 0.7: light bounces inside it) in a scene of
    unbounded depth: the job measures the depth its images need, says so, and recovers the
    colour as the unbounded reference shows it; a depth the user sets stands, and one far too
    shallow (2) leaves the colour off, which is what a cut too shallow would do."""
    key, truth = "shape_2.bsdf.base_color.value", np.array([0.41, 0.82, 0.99])
    scene = create_scene(stubs, {"s.xml": UNBOUNDED.encode()}, "s.xml", resx=24, resy=24)
    ref = stubs.scenes.RenderScene(pb.RenderSceneRequest(name=scene.name, spp=1024,
                                                         seed=3)).images[0]

    def run(scene: pb.Scene) -> tuple[pb.Job, float]:
        spec = pb.JobSpec(scene=scene.name, iterations=40, spp=16, min_error=0,
                          references=[pb.Reference(blob=ref.exr_blob)],
                          parameters=[pb.ParameterSpec(key=key, initial_value=[0.3] * 3)])
        name = stubs.jobs.CreateJob(pb.CreateJobRequest(spec=spec)).name
        job = wait_state(stubs, name, (pb.JOB_STATE_SUCCEEDED, pb.JOB_STATE_FAILED))
        assert job.state == pb.JOB_STATE_SUCCEEDED, job.error
        last = stubs.jobs.GetJobResult(pb.GetJobResultRequest(name=name, which=pb.WHICH_LAST))
        value = np.array(next(v.value for v in last.parameters if v.key == key))
        return job, float(np.sqrt(np.mean((value - truth) ** 2) / np.mean(truth ** 2)))

    job, error = run(scene)
    cut = re.search(r"max_depth (\d+) \(the scene's unbounded cut: the bounces past \d+ change "
                    r"the image by", job.integrator_reason)
    assert cut and 2 < int(cut.group(1)) < 64, job.integrator_reason
    depth = next(c for c in job.choices if c.name == "depth")
    assert depth.on and depth.setup_seconds > 0 and f"max_depth {cut.group(1)}" in depth.why
    assert error < 0.03, error

    shallow = create_scene(stubs, {"s.xml": UNBOUNDED.encode()}, "s.xml", resx=24, resy=24,
                           max_depth=2)
    job, shallow_error = run(shallow)
    assert "max_depth 2 (the scene's)" in job.integrator_reason
    assert "depth" not in {c.name for c in job.choices}
    assert shallow_error > 2 * max(error, 0.02), (shallow_error, error)


def test_a_paused_job_goes_on_with_the_choices_it_would_have_had(tmp_path):
    """The choices' state travels in the checkpoint. A near-specular glass ball whose eta is
    differenced at every iteration while it moves and every EVERY-th once it has settled
    (its recent path decides), paused after that and resumed on single-thread workers
    (deterministic sums), has the losses and etas of one that was not paused; restarted
    without its path, eta would be differenced, and stepped, at every iteration again."""
    daemon = Daemon(tmp_path / "data", None, "--workers", "2").start()
    try:
        own = Stubs(daemon.address)
        scene = create_scene(own, {"g.xml": glass(1.5, alpha=0.01).encode()}, "g.xml")
        ref = own.scenes.RenderScene(pb.RenderSceneRequest(name=scene.name, spp=128)).images[0]
        eta = "ball.bsdf.eta"
        spec = pb.JobSpec(scene=scene.name, iterations=160, min_error=0,
                          references=[pb.Reference(blob=ref.exr_blob)],
                          parameters=[pb.ParameterSpec(key=eta, initial_value=[1.35])])
        whole = own.jobs.CreateJob(pb.CreateJobRequest(spec=spec))
        whole = wait_state(own, whole.name, (pb.JOB_STATE_SUCCEEDED,), timeout=600)
        paused = own.jobs.CreateJob(pb.CreateJobRequest(spec=spec))
        wait_iteration(own, paused.name, 60)
        own.jobs.PauseJob(pb.PauseJobRequest(name=paused.name))
        at_pause = wait_state(own, paused.name, (pb.JOB_STATE_PAUSED,))
        at = at_pause.iteration
        # Paused before its end: a step call runs ~0.25 s of iterations past the request, which
        # on a replayed recording is up to ~20 of them; 100 leave room on a loaded machine
        # (60 of 120 did not, once).
        assert 60 <= at < 160
        # ... and after eta went sparse (else the comparison proves nothing)
        sparse = re.search(r"(\d+) iterations on the kept mean", next(
            c.why for c in at_pause.choices if c.name == "eta_differences"))
        assert sparse and int(sparse.group(1)) >= 1, at_pause.choices
        own.jobs.ResumeJob(pb.ResumeJobRequest(name=paused.name))
        done = wait_state(own, paused.name, (pb.JOB_STATE_SUCCEEDED,), timeout=600)
        assert done.resumed_from == f"checkpoint at iteration {at}", done.resumed_from
        runs = [own.jobs.GetJobHistory(pb.GetJobHistoryRequest(name=j.name)).iterations
                for j in (whole, paused)]
        for field in (lambda r: r.loss, lambda r: r.parameters[0].value[0]):
            np.testing.assert_allclose([field(r) for r in runs[1]],
                                       [field(r) for r in runs[0]], rtol=2e-5)
        # Both skipped the same differences in all.
        skipped = [re.search(r"(\d+) iterations on the kept mean", next(
            c.why for c in j.choices if c.name == "eta_differences")) for j in (whole, done)]
        assert skipped[0] and int(skipped[0].group(1)) >= 3
        assert skipped[1] and skipped[1].group(1) == skipped[0].group(1)
        own.close()
    finally:
        daemon.stop()


def test_the_hold_restores_where_it_stood():
    """EtaHold's state (when it was released, and the medium's recent path) sets up a hold
    that decides as the saved one would."""
    settings = api.JobSettings(
        api.SceneInput("k", "s.xml", {}, {}, "s.xml"), [],
        [api.ParameterSetting("obj.eta", 0.01, 1.001, 4.0),
         api.ParameterSetting("m.albedo.value.value", 0.03, 0.0, 1.0)], iterations=100)
    records = _records(settings, {"obj.eta": np.array([1.5]),
                                  "m.albedo.value.value": np.array([0.1] * 3)})
    hold = EtaHold(settings)
    _set_up([hold], settings, records)
    assert hold.applies and hold.released == -1
    for n in range(WINDOW):
        hold.paths["m.albedo.value.value"].add(np.array([0.1 + 0.03 * n] * 3), 0.03)
    hold.released = 42
    again = EtaHold(settings)
    _set_up([again], settings, records, hold.state())
    assert again.released == 42 and "released at iteration 42" in again.why
    # Released, eta's schedule decays from there; the medium's from the job's start.
    assert records["obj.eta"].schedule_begin == 42
    assert records["m.albedo.value.value"].schedule_begin == 0
    path = again.paths["m.albedo.value.value"]
    assert len(path.values) == WINDOW and path.rates == [0.03] * WINDOW

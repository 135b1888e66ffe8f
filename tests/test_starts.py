"""Starts compared (JobSettings.starts): a standard error describes the basin a job ended in
and cannot know of others. Probes from diverse starts can: where two end at losses within
noise of each other but at values apart, the result says the images allow several answers.
The decisions here need no renderer (engine/starts.py, engine/verdicts.py); the jobs below
run through a daemon."""

from __future__ import annotations

import csv
import json
import math

import numpy as np
import pytest

from matopt_api.v1 import matopt_pb2 as pb

from matoptd import engine_api as api
from matoptd.engine import starts, verdicts
from matoptd.engine.starts import Probe, Span

from conftest import finished, wait_state

RGB = Span("rgb", 0.0, 1.0, np.array([0.5, 0.2, 0.3], np.float32))
ROUGH = Span("scalar", 0.01, 1.0, np.array([0.3], np.float32))
OPEN = Span("scalar", 0.0, math.inf, np.array([2.0], np.float32))  # no finite range
TEXTURE = Span("texture", 0.0, 1.0, np.full(2 * 2 * 3, 0.4, np.float32), channels=3)


# -- where probes start -----------------------------------------------------------------------

def test_the_given_start_comes_first_then_middles_then_a_colours_extremes():
    found = starts.points({"c": RGB, "r": ROUGH, "u": OPEN}, 4, seed=0)
    assert np.allclose([p["c"] for p in found],
                       [[0.5, 0.2, 0.3], [0.5] * 3, [0.1] * 3, [0.9] * 3])
    # A scalar that is no colour takes its middle at a colour's extremes; an unbounded one
    # keeps its given start throughout.
    assert [float(p["r"][0]) for p in found] == pytest.approx([0.3, 0.505, 0.505, 0.505])
    assert all(float(p["u"][0]) == 2.0 for p in found)


def test_more_starts_are_drawn_from_the_ranges_by_the_seed():
    a = starts.points({"c": RGB, "t": TEXTURE}, 7, seed=3)
    assert len(a) == 7
    again, other = (starts.points({"c": RGB, "t": TEXTURE}, 7, seed=s) for s in (3, 4))
    assert all(np.array_equal(x["c"], y["c"]) for x, y in zip(a, again))
    assert not np.array_equal(a[5]["c"], other[5]["c"])
    for p in a[4:]:
        assert ((0 <= p["c"]) & (p["c"] <= 1)).all() and len(set(p["c"].tolist())) == 3
        # a texture is drawn one level per channel, not as noise
        assert np.array_equal(p["t"].reshape(-1, 3), np.tile(p["t"][:3], (4, 1)))


def test_a_job_without_a_bounded_parameter_has_one_start():
    assert len(starts.points({"u": OPEN}, 5, seed=0)) == 1


def test_probes_take_a_share_of_the_iterations_and_leave_some_to_go_on():
    assert starts.probe_length(100, 3) == 10   # max(10, 100 // 12)
    assert starts.probe_length(1000, 3) == 83
    assert starts.probe_length(8, 3) == 7      # fewer than the job's own
    assert starts.probe_length(1, 3) == 0


# -- what the probes' ends say ----------------------------------------------------------------

def test_a_probe_ends_at_the_mean_of_its_last_losses_with_noise_about_their_trend():
    descending = [1.0, 0.9, 0.8, 0.7, 0.6, 0.5, 0.4]
    loss, noise = starts.ending(descending, window=1)
    assert loss == pytest.approx(0.6) and noise == pytest.approx(0.0, abs=1e-9)
    noisy = [0.5, 0.52, 0.48, 0.51, 0.49]
    assert starts.ending(noisy, 1)[1] > 0.005
    assert starts.ending([math.nan, 0.3], 1) == (0.3, 0.0)


def _probe(index: int, value: float, loss: float, noise: float = 0.001) -> Probe:
    return Probe(index, {}, {"c": np.array([0.5, 0.5, value], np.float32)}, loss, noise, 10)


def test_probes_at_the_same_loss_and_other_values_are_several_answers():
    probes = [_probe(0, 0.2, 0.0101), _probe(1, 0.8, 0.0100), _probe(2, 0.5, 0.05)]
    found = starts.several(probes, {"c": RGB})
    # the third component differs; the probe the job goes on from comes first (the given
    # start: the second's loss is lower by less than the noise); the third's loss is far
    # above the noise, so its value is no answer
    assert starts.best(probes) is probes[0]
    assert list(found) == ["c"] and found["c"][:2] == [[], []]
    assert found["c"][2] == [(pytest.approx(0.2), 0.0101), (pytest.approx(0.8), 0.0100)]
    assert starts.reason(found["c"][2]) == ("the images allow several answers: 0.2 (loss "
                                            "0.0101), 0.8 (loss 0.01)")


def test_the_job_leaves_the_given_start_only_for_a_loss_lower_beyond_noise():
    given, lucky, better = (_probe(0, 0.5, 0.01263, 0.0004), _probe(1, 0.5, 0.01258, 0.0004),
                            _probe(2, 0.5, 0.009, 0.0004))
    assert starts.best([given, lucky]) is given
    assert starts.best([given, lucky, better]) is better
    assert starts.best([_probe(0, 0.5, math.nan), lucky]) is lucky


def test_a_loss_above_the_noise_or_values_within_the_interval_are_one_answer():
    assert starts.several([_probe(0, 0.2, 0.02), _probe(1, 0.8, 0.01)], {"c": RGB}) == {}
    close = [_probe(0, 0.50, 0.01), _probe(1, 0.53, 0.01)]
    assert starts.several(close, {"c": RGB}) == {}  # 0.03 apart: less than a tenth of the range
    # with an interval, apart is outside it: +-2 standard errors of 0.001 do not reach 0.03
    errors = {"c": np.array([0.001] * 3)}
    assert starts.several(close, {"c": RGB}, errors)["c"][2]


def test_a_value_still_on_its_way_is_no_answer():
    """A probe from 1.5 towards an eta of 2.5, at 1.87 after 10 iterations and moving 0.03
    an iteration, can tie in loss with one at 2.63: at its pace it would go 3 in the 100
    iterations left, so its 1.87 is no answer. Settled, it is."""
    eta = Span("scalar", 1.0, 4.0, np.array([1.5], np.float32))
    path = [{"eta": np.array([1.72 + 0.03 * i], np.float32)} for i in range(6)]
    reach = starts.reach(path, left=100)
    assert reach["eta"] == pytest.approx([3.0], rel=1e-3)
    moving = Probe(0, {}, {"eta": np.array([1.87], np.float32)}, 0.001674, 2e-5, 10, reach)
    settled = Probe(1, {}, {"eta": np.array([2.63], np.float32)}, 0.001766, 5.6e-5, 10,
                    {"eta": np.array([0.1])})
    assert starts.several([moving, settled], {"eta": eta}) == {}
    moving.reach = {"eta": np.array([0.2])}
    assert starts.several([moving, settled], {"eta": eta})["eta"][0]


def test_the_verdict_says_several_answers_instead_of_an_interval():
    said = verdicts.Verdicts(
        {"c": api.StandardError(np.array([0.01, 0.01, 0.01], np.float32), ["two_sided"] * 3)},
        {}, ["a note"])
    probes = [_probe(0, 0.2, 0.01), _probe(1, 0.8, 0.01)]
    out = verdicts.several(said, probes, {"c": RGB})
    c = out.errors["c"]
    assert c.reading == ["two_sided", "two_sided", "not_determined"]
    assert np.isinf(c.error[2]) and c.error[0] == pytest.approx(0.01)
    assert c.reason == ["", "", "the images allow several answers: 0.2 (loss 0.01), "
                                "0.8 (loss 0.01)"]
    assert verdicts.several(said, probes[:1], {"c": RGB}) is said  # one start: as it was


def test_a_texture_with_several_answers_gets_a_note():
    probes = [Probe(i, {}, {"t": np.full(12, v, np.float32)}, 0.01, 0.0, 10)
              for i, v in enumerate((0.2, 0.7))]
    out = verdicts.several(verdicts.Verdicts({}, {}, []), probes, {"t": TEXTURE})
    assert out.notes == ["t: the images allow several answers: 0.2 (loss 0.01), "
                         "0.7 (loss 0.01)"]


# -- through a daemon -------------------------------------------------------------------------

@pytest.fixture(scope="module")
def quads(stubs):
    """test_verdicts' scene: a colour in view, a dark grey quad (0.12) in view, and a quad out
    of view whose colour no image sees; and a reference of it."""
    from scenes import create_scene
    from test_verdicts import three_quads
    scene = create_scene(stubs, {"quads.xml": three_quads().encode()}, "quads.xml")
    ref = stubs.scenes.RenderScene(pb.RenderSceneRequest(name=scene.name, spp=128)).images[0]
    return scene, pb.Reference(blob=ref.exr_blob)


def _history(stubs, name: str) -> list[pb.IterationRecord]:
    return list(stubs.jobs.GetJobHistory(pb.GetJobHistoryRequest(name=name)).iterations)


def test_starts_outside_1_to_8_are_refused_naming_the_setting(stubs, quads):
    import grpc
    scene, ref = quads
    for n in (0, 9):
        with pytest.raises(grpc.RpcError) as err:
            stubs.jobs.CreateJob(pb.CreateJobRequest(spec=pb.JobSpec(
                scene=scene.name, references=[ref], starts=n,
                parameters=[pb.ParameterSpec(key=AT_BOUND)])))
        assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT
        assert err.value.details() == f"starts must be 1 to 8, got {n}"
    assert stubs.server.GetServerInfo(pb.GetServerInfoRequest()).variant  # still serving


SEEN, AT_BOUND, HIDDEN = ("seen.bsdf.reflectance.value", "dark.bsdf.reflectance.value",
                          "hidden.bsdf.reflectance.value")


@pytest.fixture(scope="module")
def several(stubs, quads) -> tuple[pb.Job, pb.JobResult]:
    """The hidden quad's colour changes no image: probes from its given start (0.3) and its
    range's middle (0.5) render alike, end at the same loss and keep their values."""
    scene, ref = quads
    return finished(stubs, pb.JobSpec(
        scene=scene.name, references=[ref], iterations=30, spp=8, starts=3,
        parameters=[pb.ParameterSpec(key=SEEN, initial_value=[0.5] * 3),
                    pb.ParameterSpec(key=HIDDEN, initial_value=[0.3])]))


def test_probes_that_end_alike_at_other_values_say_the_images_allow_several_answers(
        stubs, several):
    """The result lists both answers with their loss; the colour in view, which every probe
    recovers alike, keeps its interval."""
    done, result = several
    assert done.spec.starts == 3
    probes = [n for n in done.notes if n.startswith("probe ")]
    assert [n.split(":")[0] for n in probes] == [f"probe {k} of 3" for k in (1, 2, 3)]
    assert any("goes on from probe 1 " in n for n in done.notes), done.notes  # a tie: given
    # The best probe's iterations are the job's first: 30 in all, from 0.
    history = _history(stubs, done.name)
    assert [h.iteration for h in history] == list(range(30))
    assert done.elapsed_seconds >= history[-1].seconds > 0
    values = {p.key: p for p in result.parameters}
    hidden, seen = values[HIDDEN], values[SEEN]
    assert list(hidden.interval) == [pb.INTERVAL_NOT_DETERMINED]
    reason = hidden.interval_reason[0]
    assert reason.startswith("the images allow several answers: 0.3 (loss ")
    assert ", 0.5 (loss " in reason, reason
    assert list(seen.interval) == [pb.INTERVAL_TWO_SIDED] * 3, seen


def test_every_surface_says_several_answers(several, cli_env, tmp_path):
    """As test_verdicts checks each verdict: the CLI's result and status, its --json, and the
    export's parameters.csv and parameters.json."""
    from test_cli_conventions import matopt
    done, result = several
    reason = next(p for p in result.parameters if p.key == HIDDEN).interval_reason[0]

    def run(*args: str) -> str:
        out = matopt(cli_env, *args)
        assert out.returncode == 0, out.stderr
        return out.stdout

    line = next(x for x in run("job", "result", done.name).splitlines()
                if x.startswith(f"{HIDDEN}:"))
    assert line.endswith(f"(not determined by these images: {reason})") and "+-" not in line
    assert reason in run("job", "status", done.name)
    document = json.loads(run("job", "result", done.name, "--json"))
    hidden = next(p for p in document["parameters"] if p["key"] == HIDDEN)
    assert hidden["intervalReason"] == [reason]
    assert "3 starts compared" in run("job", "status", done.name)
    run("job", "export", done.name, "--out", str(tmp_path / "out"))
    with open(tmp_path / "out" / "parameters.csv") as f:
        rows = {(r["parameter"], int(r["component"])): r for r in csv.DictReader(f)}
    assert rows[(HIDDEN, 0)]["interval"] == "not_determined"
    assert rows[(HIDDEN, 0)]["reason"] == reason
    exported = json.loads((tmp_path / "out" / "parameters.json").read_text())
    assert exported["reasons"][HIDDEN] == [reason]


# Enough that the pause lands before the job ends (30 iterations at 32 px took 0.15 s, and
# the pause came after them).
ITERATIONS = 600


def test_a_job_paused_as_its_probes_run_keeps_them_and_their_verdict(stubs, quads):
    """Paused at once, the job's probes finish in the call that loads it, and the checkpoint
    the pause takes holds them: the resumed job runs none again, its history counts each
    iteration once, and its result still says where the probes found several answers."""
    scene, ref = quads
    job = stubs.jobs.CreateJob(pb.CreateJobRequest(spec=pb.JobSpec(
        scene=scene.name, references=[ref], iterations=ITERATIONS, spp=8, starts=2,
        parameters=[pb.ParameterSpec(key=HIDDEN, initial_value=[0.3]),
                    pb.ParameterSpec(key=SEEN, initial_value=[0.5] * 3)])))
    stubs.jobs.PauseJob(pb.PauseJobRequest(name=job.name))
    wait_state(stubs, job.name, (pb.JOB_STATE_PAUSED,))
    stubs.jobs.ResumeJob(pb.ResumeJobRequest(name=job.name))
    done = wait_state(stubs, job.name, (pb.JOB_STATE_SUCCEEDED, pb.JOB_STATE_FAILED))
    assert done.state == pb.JOB_STATE_SUCCEEDED, done.error
    assert sum(n.startswith("probe 1 of 2") for n in done.notes) == 1, done.notes
    assert [h.iteration for h in _history(stubs, job.name)] == list(range(ITERATIONS))
    result = stubs.jobs.GetJobResult(pb.GetJobResultRequest(name=job.name))
    hidden = next(p for p in result.parameters if p.key == HIDDEN)
    assert hidden.interval_reason[0].startswith("the images allow several answers: 0.3 ")


def test_a_bad_start_that_one_probe_cannot_leave_is_left_for_a_better_one(stubs, quads):
    """The dark quad (truth 0.12) started at 0.9 with a slow rate: 30 iterations from there
    end near 0.44; three starts (0.9, the middle 0.5, one drawn) go on from the middle's
    probe and end within 0.05 of the truth."""
    scene, ref = quads

    def run(starts: int) -> tuple[pb.Job, float]:
        done, result = finished(stubs, pb.JobSpec(
            scene=scene.name, references=[ref], iterations=30, spp=8, starts=starts,
            learning_rate=0.03, parameters=[pb.ParameterSpec(key=AT_BOUND,
                                                             initial_value=[0.9])]))
        return done, next(p.value[0] for p in result.parameters if p.key == AT_BOUND)

    one, alone = run(1)
    three, compared = run(3)
    assert abs(alone - 0.12) > 0.2, alone
    assert abs(compared - 0.12) < 0.05, (compared, three.notes)
    assert not any(n.startswith("probe ") for n in one.notes)
    # the middle (0.5) ends nearest after its probe: the job goes on from it
    assert any("goes on from probe 2 " in n for n in three.notes), three.notes

"""A data dir of an earlier release (protobuf rows, ``legacy_store``) opens in this one: its
scenes, jobs, histories, results and checkpoints come back as they were, and its unfinished jobs
resume from their checkpoints, the first release's blob checkpoints included."""

from __future__ import annotations

import hashlib
import json
import sqlite3

import pytest

from matopt_api.v1 import matopt_pb2 as pb

import legacy_store
from conftest import Daemon, Stubs, wait_state
from matoptd.store.store import Store
from test_faults import wait_iteration

# The Cornell box's true wall colours (mitsuba.cornell_box()), as ground truth.
WALLS = {"red.reflectance.value": [0.570068, 0.0430135, 0.0443706],
         "green.reflectance.value": [0.105421, 0.37798, 0.076425]}


ITERATIONS = 400  # of the jobs paused before the migration


def job(stubs: Stubs, scene: str, ref: str, iterations: int, **spec) -> pb.Job:
    return stubs.jobs.CreateJob(pb.CreateJobRequest(spec=pb.JobSpec(
        scene=scene, iterations=iterations, spp=2, seed=3,
        references=[pb.Reference(blob=ref, filename="ref.exr")],
        parameters=[pb.ParameterSpec(key=k, initial_value=[0.5] * 3) for k in WALLS],
        **spec)))


def paused(stubs: Stubs, name: str) -> pb.Job:
    wait_iteration(stubs, name, 12)
    stubs.jobs.PauseJob(pb.PauseJobRequest(name=name))
    return wait_state(stubs, name, (pb.JOB_STATE_PAUSED,))


def answers(stubs: Stubs, jobs: list[str]) -> legacy_store.Answers:
    out = legacy_store.Answers("local")
    for scene in stubs.scenes.ListScenes(pb.ListScenesRequest()).scenes:
        out.scenes.append((scene, stubs.scenes.ListSceneParameters(
            pb.ListSceneParametersRequest(name=scene.name))))
    for name in jobs:
        out.jobs.append(stubs.jobs.GetJob(pb.GetJobRequest(name=name)))
        out.histories[name] = list(stubs.jobs.GetJobHistory(
            pb.GetJobHistoryRequest(name=name)).iterations)
        for which in (pb.WHICH_BEST, pb.WHICH_LAST):
            try:
                out.results.append(stubs.jobs.GetJobResult(
                    pb.GetJobResultRequest(name=name, which=which)))
            except Exception:  # noqa: BLE001 - a paused job has none yet
                pass
    return out


def same_time(a, b) -> bool:
    return abs(a.ToNanoseconds() - b.ToNanoseconds()) < 1000


def test_a_data_dir_of_the_protobuf_release_comes_back_whole_and_resumes(tmp_path):
    data = tmp_path / "data"
    daemon = Daemon(data).start()
    stubs = Stubs(daemon.address)
    try:
        scene = stubs.scenes.CreateScene(pb.CreateSceneRequest(overrides={"resx": "16",
                                                                          "resy": "16"}))
        ref = stubs.scenes.RenderScene(pb.RenderSceneRequest(name=scene.name, spp=16)).images[0]
        done = job(stubs, scene.name, ref.exr_blob, 6, ground_truth=[
            pb.ParameterValue(key=k, value=v) for k, v in WALLS.items()])
        done = wait_state(stubs, done.name, (pb.JOB_STATE_SUCCEEDED,))
        # Long enough that a pause asked at iteration 12 lands before the end: on a CPU host
        # the server answers behind the render (nice 19), and 40 iterations took 0.44 s.
        kept = paused(stubs, job(stubs, scene.name, ref.exr_blob, ITERATIONS).name)
        crashed = paused(stubs, job(stubs, scene.name, ref.exr_blob, ITERATIONS).name)
        before = answers(stubs, [done.name, kept.name, crashed.name])
    finally:
        stubs.close()
        daemon.stop()

    db = sqlite3.connect(data / "matoptd.sqlite3")
    inputs = {name: json.loads(record)["inputs"]
              for name, record in db.execute("SELECT name, record FROM scenes")}
    owners = db.execute("SELECT sha256, owner, size FROM blob_owners").fetchall()
    db.close()
    inputs = {n: {k: i[k] for k in ("main_file", "files", "overrides", "display")}
              for n, i in inputs.items()}
    # The first release kept a checkpoint as a blob; one job's is moved there.
    checkpoint = data / "checkpoints" / f"{crashed.name.removeprefix('jobs/')}.npz"
    blob = hashlib.sha256(checkpoint.read_bytes()).hexdigest()
    (data / "blobs" / blob[:2]).mkdir(exist_ok=True)
    (data / "blobs" / blob[:2] / blob).write_bytes(checkpoint.read_bytes())
    checkpoint.unlink()
    legacy_store.write(data, before, inputs, owners,
                       states={crashed.name: pb.JOB_STATE_RUNNING},  # the old daemon crashed
                       checkpoint_blobs={crashed.name: f"blobs/{blob}"})

    daemon = Daemon(data).start()
    stubs = Stubs(daemon.address)
    try:
        after = answers(stubs, [done.name, kept.name, crashed.name])
        assert [s for s, _ in after.scenes] == [s for s, _ in before.scenes]
        assert [p for _, p in after.scenes] == [p for _, p in before.scenes]
        assert after.histories == before.histories
        assert after.results == before.results
        old, new = before.jobs[0], after.jobs[0]
        assert same_time(old.create_time, new.create_time)
        assert same_time(old.update_time, new.update_time)
        for j in (old, new):
            j.ClearField("create_time")
            j.ClearField("update_time")
        assert new == old  # the spec with every default filled in, as before
        assert after.jobs[1].state == pb.JOB_STATE_PAUSED
        interrupted = after.jobs[2]
        assert (interrupted.state, interrupted.stop_reason) == (
            pb.JOB_STATE_INTERRUPTED, "the daemon stopped while the job ran")

        for j in (kept, crashed):
            stubs.jobs.ResumeJob(pb.ResumeJobRequest(name=j.name))
        for j in (kept, crashed):
            end = wait_state(stubs, j.name, (pb.JOB_STATE_SUCCEEDED, pb.JOB_STATE_FAILED))
            assert end.state == pb.JOB_STATE_SUCCEEDED, end.error
            assert end.resumed_from == f"checkpoint at iteration {j.iteration}"
            history = stubs.jobs.GetJobHistory(pb.GetJobHistoryRequest(name=j.name))
            assert [r.iteration for r in history.iterations] == list(range(ITERATIONS))
        assert "data dir upgraded to version 2: 1 scenes, 3 jobs" in daemon.log.read_text()
    finally:
        stubs.close()
        daemon.stop()


def test_a_data_dir_of_a_newer_version_is_refused_untouched(tmp_path):
    Store(tmp_path).close()
    db = sqlite3.connect(tmp_path / "matoptd.sqlite3")
    db.execute("PRAGMA user_version=3")
    db.commit()
    db.close()
    with pytest.raises(RuntimeError) as err:
        Store(tmp_path)
    assert str(err.value) == ("the data dir's database is of version 3, made by a newer "
                              "matoptd; this one reads up to version 2")
    db = sqlite3.connect(tmp_path / "matoptd.sqlite3")
    assert db.execute("PRAGMA user_version").fetchone() == (3,)

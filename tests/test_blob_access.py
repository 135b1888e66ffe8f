"""Blobs belong to users: another user's upload or render is as absent as one never made, equal
content is stored once, a user deletes what is theirs, and a quota bounds what they keep."""

from __future__ import annotations

import hashlib
import io
import json
import os
import sqlite3
import subprocess
import sys

import grpc
import numpy as np
import pytest

from matopt_api.v1 import matopt_pb2 as pb

from conftest import Daemon, Stubs, TOKENS, token_file, wait_state
from matoptd.records import BundleFile, ImageRef, JobRecord, ResultRecord, SceneRecord
from matoptd.settings import JobSettings, ReferenceInput, SceneInput
from matoptd.store.store import Store
from scenes import camera, upload

USERS = {**TOKENS, "carol": "carol-token-0123456789"}
QUOTA = 4 << 20  # carol's tests fill it; alice's and bob's work stays far below
RED = "red.reflectance.value"

SPHERE = f"""<scene version="3.0.0">
    {camera(16)}
    <emitter type="constant"/>
    <shape type="sphere" id="ball"><bsdf type="diffuse"/></shape>
</scene>
""".encode()


@pytest.fixture(scope="module")
def daemon(tmp_path_factory):
    root = tmp_path_factory.mktemp("blob-access")
    tokens = token_file(root, USERS)
    d = Daemon(root / "data", tokens, "--quota", "4M").start()
    yield d
    d.stop()


@pytest.fixture
def users(daemon):
    """Stubs for alice, bob and carol on the daemon as it runs now (a test may restart it)."""
    stubs = {u: Stubs(daemon.address, t) for u, t in USERS.items()}
    yield stubs
    for s in stubs.values():
        s.close()


def rpc_error(call, *args) -> grpc.RpcError:
    with pytest.raises(grpc.RpcError) as err:
        call(*args)
    return err.value


def download(stubs: Stubs, name: str) -> bytes:
    return b"".join(r.chunk for r in stubs.blobs.DownloadBlob(pb.DownloadBlobRequest(name=name)))


def missing(stubs: Stubs, *digests: str) -> list[str]:
    return list(stubs.blobs.FindMissingBlobs(pb.FindMissingBlobsRequest(sha256=digests))
                .missing_sha256)


def npy(values) -> bytes:
    buf = io.BytesIO()
    np.save(buf, np.asarray(values, dtype=np.float32))
    return buf.getvalue()


def bare(name: str) -> str:
    return name.removeprefix("blobs/")


def assert_as_if_absent(call, theirs: str) -> None:
    """``call(digest)`` fails for another user's blob exactly as for one nobody has: NOT_FOUND,
    and the same message with the digest swapped."""
    never = hashlib.sha256(os.urandom(16)).hexdigest()
    hidden, absent = rpc_error(call, theirs), rpc_error(call, never)
    assert hidden.code() == absent.code() == grpc.StatusCode.NOT_FOUND, hidden.details()
    assert f"blobs/{theirs}" in hidden.details()
    assert hidden.details().replace(theirs, never) == absent.details()


def cornell(stubs: Stubs, res: int = 16) -> tuple[pb.Scene, pb.Image]:
    """A scene and a render of it; the seed makes the render's content this call's alone
    (two users' equal renders would be one blob that both own)."""
    scene = stubs.scenes.CreateScene(pb.CreateSceneRequest(
        overrides={"resx": str(res), "resy": str(res)}))
    render = stubs.scenes.RenderScene(pb.RenderSceneRequest(
        name=scene.name, spp=4, seed=int.from_bytes(os.urandom(4), "little")))
    return scene, render.images[0]


def job_request(scene: pb.Scene, ref: str, iterations: int = 2, **parameter) -> pb.CreateJobRequest:
    return pb.CreateJobRequest(spec=pb.JobSpec(
        scene=scene.name, iterations=iterations, spp=2,
        references=[pb.Reference(blob=f"blobs/{bare(ref)}", filename="ref.exr")],
        parameters=[pb.ParameterSpec(key=RED, **parameter)]))


def blob_file(daemon: Daemon, sha: str):
    return daemon.data_dir / "blobs" / sha[:2] / sha


def test_another_users_upload_and_render_are_not_found(users):
    alice, bob = users["alice"], users["bob"]
    data = os.urandom(3000)
    sha = upload(alice, data)
    _, render = cornell(alice)
    renders = [bare(render.exr_blob), bare(render.png_blob)]

    assert missing(alice, sha, *renders) == []
    assert missing(bob, sha, *renders) == [sha, *renders]
    for theirs in (sha, *renders):
        assert_as_if_absent(lambda s: download(bob, f"blobs/{s}"), theirs)
    assert download(alice, f"blobs/{sha}") == data
    assert download(alice, render.png_blob).startswith(b"\x89PNG")


def test_another_users_blob_cannot_be_used_until_uploaded_again(users, daemon):
    alice, bob = users["alice"], users["bob"]
    _, alice_render = cornell(alice)
    ref = bare(alice_render.exr_blob)
    values = npy([0.3, 0.2, 0.1])
    xml, start = upload(alice, SPHERE), upload(alice, values)
    bob_scene, bob_render = cornell(bob)

    def create_scene(s):
        return bob.scenes.CreateScene(pb.CreateSceneRequest(
            main_file="sphere.xml", files=[pb.BundleFile(path="sphere.xml", sha256=s)]))

    def with_reference(s):
        return bob.jobs.CreateJob(job_request(bob_scene, s))

    def with_initial(s):
        return bob.jobs.CreateJob(job_request(bob_scene, bob_render.exr_blob,
                                              initial_blob=f"blobs/{s}"))

    def with_truth(s):
        request = job_request(bob_scene, bob_render.exr_blob)
        request.spec.ground_truth.append(pb.ParameterValue(key=RED, blob=f"blobs/{s}"))
        return bob.jobs.CreateJob(request)

    def render(s):
        return bob.scenes.RenderScene(pb.RenderSceneRequest(
            name=bob_scene.name, spp=1, parameters=[pb.ParameterValue(key=RED, blob=f"blobs/{s}")]))

    for call, theirs in ((create_scene, xml), (with_reference, ref), (with_initial, start),
                         (with_truth, start), (render, start)):
        assert_as_if_absent(call, theirs)
    assert "bundle file 'sphere.xml'" in rpc_error(create_scene, xml).details()

    # Once bob uploads the same content it is his too, kept on disk once.
    assert missing(bob, ref, xml, start) == [ref, xml, start]
    for data in (download(alice, f"blobs/{ref}"), SPHERE, values):
        upload(bob, data)
    assert missing(bob, ref, xml, start) == []
    assert [p.name for p in blob_file(daemon, ref).parent.iterdir()].count(ref) == 1
    assert create_scene(xml).display_name == "sphere.xml"
    assert render(start).images[0].exr_blob
    assert with_truth(start).spec.ground_truth[0].blob == f"blobs/{start}"
    job = bob.jobs.CreateJob(job_request(bob_scene, ref, initial_blob=f"blobs/{start}"))
    # What bob's job writes is bob's, not alice's.
    wait_state(bob, job.name, (pb.JOB_STATE_SUCCEEDED,), timeout=300)
    result = bob.jobs.GetJobResult(pb.GetJobResultRequest(name=job.name))
    optimized = next(i for i in result.images if i.role == "optimized")
    assert download(bob, optimized.exr_blob)
    assert missing(alice, bare(optimized.exr_blob)) == [bare(optimized.exr_blob)]


def test_a_blob_in_use_is_kept_and_the_last_owner_frees_the_disk(users, daemon):
    alice, bob = users["alice"], users["bob"]
    data = os.urandom(2000)
    sha = upload(alice, data)
    assert upload(bob, data) == sha
    path = blob_file(daemon, sha)

    # Bob cannot delete what is only alice's, nor learn from trying that it exists.
    only_alice = upload(alice, os.urandom(100))
    assert_as_if_absent(lambda s: bob.blobs.DeleteBlob(pb.DeleteBlobRequest(name=s)), only_alice)
    assert missing(alice, only_alice) == []

    alice.blobs.DeleteBlob(pb.DeleteBlobRequest(name=f"blobs/{sha}"))
    assert path.exists() and download(bob, f"blobs/{sha}") == data
    assert missing(alice, sha) == [sha]
    assert rpc_error(download, alice, f"blobs/{sha}").code() == grpc.StatusCode.NOT_FOUND
    bob.blobs.DeleteBlob(pb.DeleteBlobRequest(name=sha))  # the bare digest works too
    assert not path.exists()
    err = rpc_error(bob.blobs.DeleteBlob, pb.DeleteBlobRequest(name=sha))
    assert err.code() == grpc.StatusCode.NOT_FOUND and sha in err.details()

    # A scene's file and a job's reference stay while the scene and the job do.
    xml = upload(alice, SPHERE)
    scene = alice.scenes.CreateScene(pb.CreateSceneRequest(
        main_file="sphere.xml", files=[pb.BundleFile(path="sphere.xml", sha256=xml)]))
    cornell_scene, render = cornell(alice)
    job = alice.jobs.CreateJob(job_request(cornell_scene, render.exr_blob, iterations=100000))
    for name, user in ((f"blobs/{xml}", scene.name), (render.exr_blob, job.name)):
        err = rpc_error(alice.blobs.DeleteBlob, pb.DeleteBlobRequest(name=name))
        assert err.code() == grpc.StatusCode.FAILED_PRECONDITION
        assert f"'{name}' is used by {user}" in err.details(), err.details()
    listed = {b.name: b for b in alice.blobs.ListBlobs(pb.ListBlobsRequest(page_size=1000)).blobs}
    assert list(listed[f"blobs/{xml}"].used_by) == [scene.name]
    assert list(listed[render.exr_blob].used_by) == [job.name]
    assert listed[f"blobs/{xml}"].size_bytes == len(SPHERE)

    alice.scenes.DeleteScene(pb.DeleteSceneRequest(name=scene.name))
    alice.blobs.DeleteBlob(pb.DeleteBlobRequest(name=f"blobs/{xml}"))
    assert missing(alice, xml) == [xml]
    alice.jobs.CancelJob(pb.CancelJobRequest(name=job.name))
    wait_state(alice, job.name, (pb.JOB_STATE_CANCELLED,))
    alice.jobs.DeleteJob(pb.DeleteJobRequest(name=job.name))
    alice.blobs.DeleteBlob(pb.DeleteBlobRequest(name=render.exr_blob))
    assert not blob_file(daemon, bare(render.exr_blob)).exists()


def usage(stubs: Stubs) -> int:
    return stubs.blobs.ListBlobs(pb.ListBlobsRequest()).used_bytes


def test_quota_refuses_uploads_keeps_results_and_then_refuses_new_work(users):
    carol = users["carol"]
    big = upload(carol, os.urandom(3 << 20))
    err = rpc_error(upload, carol, os.urandom(2 << 20))
    assert err.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
    assert "would exceed your quota of 4.0 MiB (4194304 bytes)" in err.details(), err.details()
    assert "your blobs use 3.0 MiB" in err.details()

    # Just below the quota a job is still accepted, and its results are kept past it.
    scene, render = cornell(carol)
    fill = QUOTA - usage(carol) - 1
    filler = upload(carol, os.urandom(fill))
    listing = carol.blobs.ListBlobs(pb.ListBlobsRequest())
    assert (listing.used_bytes, listing.quota_bytes) == (QUOTA - 1, QUOTA)
    job = carol.jobs.CreateJob(job_request(scene, render.exr_blob))
    wait_state(carol, job.name, (pb.JOB_STATE_SUCCEEDED,), timeout=300)
    result = carol.jobs.GetJobResult(pb.GetJobResultRequest(name=job.name))
    assert all(download(carol, i.png_blob).startswith(b"\x89PNG") for i in result.images)
    used = usage(carol)
    assert used > QUOTA

    for call, request in ((carol.scenes.RenderScene, pb.RenderSceneRequest(name=scene.name)),
                          (carol.jobs.CreateJob, job_request(scene, render.exr_blob)),
                          (carol.scenes.CreateScene, pb.CreateSceneRequest())):
        err = rpc_error(call, request)
        assert err.code() == grpc.StatusCode.RESOURCE_EXHAUSTED, call
        assert "of your quota of 4.0 MiB" in err.details() and "DeleteBlob" in err.details()
    assert rpc_error(upload, carol, b"x").code() == grpc.StatusCode.RESOURCE_EXHAUSTED

    for sha in (big, filler):
        carol.blobs.DeleteBlob(pb.DeleteBlobRequest(name=sha))
    assert usage(carol) == used - (3 << 20) - fill
    assert carol.scenes.RenderScene(pb.RenderSceneRequest(name=scene.name, spp=1)).images


def test_cli_lists_and_deletes_blobs(users, daemon, tmp_path):
    bob = users["bob"]
    unused = upload(bob, os.urandom(1500))
    _, render = cornell(bob)  # the render is used by nothing either

    def matopt(*args):
        return subprocess.run([sys.executable, "-m", "matopt_client.cli", "--server", daemon.address,
                               "--token", USERS["bob"], "blob", *args],
                              capture_output=True, text=True, timeout=120)

    listing = matopt("list")
    assert listing.returncode == 0, listing.stderr
    assert f"blobs/{unused}" in listing.stdout and "(no quota)" not in listing.stderr
    assert "of your quota of 4.0 MiB" in listing.stderr
    as_json = json.loads(matopt("list", "--json").stdout)
    names = {b["name"]: b for b in as_json["blobs"]}
    assert names[f"blobs/{unused}"]["sizeBytes"] == "1500"

    scene_xml = upload(bob, SPHERE)
    scene = bob.scenes.CreateScene(pb.CreateSceneRequest(
        main_file="s.xml", files=[pb.BundleFile(path="s.xml", sha256=scene_xml)]))
    refused = matopt("rm", scene_xml)
    assert refused.returncode == 1
    assert refused.stderr.count("\n") == 1 and "FAILED_PRECONDITION" in refused.stderr
    assert scene.name in refused.stderr

    gone = matopt("rm", "--unused")
    assert gone.returncode == 0, gone.stderr
    assert f"deleted blobs/{unused}" in gone.stderr and f"deleted {render.exr_blob}" in gone.stderr
    assert missing(bob, unused, bare(render.exr_blob), scene_xml) == [unused,
                                                                     bare(render.exr_blob)]


def test_ownership_survives_a_restart(users, daemon):
    alice = users["alice"]
    data = os.urandom(1000)
    sha = upload(alice, data)
    daemon.restart()
    alice, bob = Stubs(daemon.address, USERS["alice"]), Stubs(daemon.address, USERS["bob"])
    try:
        assert missing(alice, sha) == [] and missing(bob, sha) == [sha]
        assert download(alice, f"blobs/{sha}") == data
        assert_as_if_absent(lambda s: download(bob, f"blobs/{s}"), sha)
    finally:
        alice.close()
        bob.close()


def test_a_data_dir_from_before_owners_gives_each_user_what_their_work_names(tmp_path):
    """Upgrading keeps every user's scenes, references and results reachable; an upload that
    nothing names is nobody's until someone uploads it again."""
    store = Store(tmp_path)
    xml = store.blobs.put(b"<scene/>", "alice")
    ref, out, orphan = (store.blobs.put(data, "alice")
                        for data in (b"reference", b"result image", b"never used"))
    inputs = SceneInput.of("s.xml", {"s.xml": xml}, {}, "s.xml")
    store.add_scene(SceneRecord("scenes/s", "alice", "s", "s.xml", [BundleFile("s.xml", xml)],
                                {}, [], [], False, 0, inputs), [], None)
    store.add_job(JobRecord("jobs/j", "bob", "scenes/s", JobSettings(
        inputs, [ReferenceInput(0, ref, "ref.png")], [])), None)
    store.put_result(ResultRecord("jobs/j", "best", 0, 0.0, {}, {}, {},
                                  [ImageRef(0, "optimized", 1, 1, out, "")], [], "", []))
    store.close()
    db = sqlite3.connect(tmp_path / "matoptd.sqlite3")
    db.execute("DROP TABLE blob_owners")  # as a data dir made before blobs had owners
    db.commit()
    db.close()

    again = Store(tmp_path)
    assert [again.blobs.owns(u, xml) for u in ("alice", "bob")] == [True, False]
    assert [again.blobs.owns(u, s) for u in ("alice", "bob") for s in (ref, out)] == [
        False, False, True, True]
    assert not again.blobs.owns("alice", orphan)
    assert (tmp_path / "blobs" / orphan[:2] / orphan).exists()
    assert again.blobs.usage("bob") == len(b"reference") + len(b"result image")
    assert again.blobs.in_use("bob") == {ref: ["jobs/j"], out: ["jobs/j"]}
    again.close()


@pytest.mark.parametrize("quota, message", [("lots", "--quota: 'lots' is not a size"),
                                            ("0", "--quota must be at least 1 byte")])
def test_a_bad_quota_is_refused_at_start(tmp_path, quota, message):
    out = subprocess.run([sys.executable, "-m", "matoptd", "--quota", quota, "--data-dir",
                          str(tmp_path / "d"), "--listen", "127.0.0.1:0"],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode != 0 and message in out.stderr, out.stderr

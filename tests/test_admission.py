"""Admission control without a daemon: cost estimates, limits, and the messages that name the
value, the limit and the flag."""

from __future__ import annotations

import numpy as np
import pytest

from matoptd import engine_api as api
from matoptd.errors import InvalidArgument, ResourceExhausted
from matoptd.server import admission
from matoptd.server.admission import Limits
from matoptd.server.image_headers import ImageHeader
from matoptd.settings import JobSettings, ReferenceInput, SceneInput

from scenes import exr, png
from test_image_headers import png_header_only

SCENE = SceneInput("k", "s.xml", {}, {}, "s.xml")
FILMS = {0: (64, 48), 1: (32, 32)}


def settings(refs: dict[int, str], **kw) -> JobSettings:
    return JobSettings(SCENE, [ReferenceInput(s, f"sha{s}", name)
                               for s, name in refs.items()], [], **kw)


def rgb(width: int, height: int) -> ImageHeader:
    return ImageHeader("PNG", width, height, 3, 3)


def test_a_job_renders_each_referenced_sensor_at_its_reference_aspect():
    est = admission.job_estimate(settings({0: "a.png", 1: "b.png"}, spp=4),
                                 FILMS, {0: rgb(200, 100), 1: rgb(30, 30)})
    assert [(r.sensor, r.width, r.height, r.spp) for r in est.renders] == [
        (0, 96, 48, 4), (1, 32, 32, 4)]
    assert est.samples_per_iteration == (96 * 48 + 32 * 32) * 4
    assert est.film_bytes == (96 * 48 + 32 * 32) * 16


def test_film_height_sets_the_height_of_every_film():
    est = admission.job_estimate(settings({1: "wide.png"}, spp=2, film_height=100), FILMS,
                                 {1: rgb(300, 100)})
    assert [(r.width, r.height) for r in est.renders] == [(300, 100)]
    assert "film_height 100" in est.renders[0].film_from
    assert "'wide.png' (300x100 px)" in est.renders[0].film_from


def test_dual_buffer_renders_twice_and_image_error_once_more():
    est = admission.job_estimate(settings({0: "a.png"}, spp=8, loss="dual_buffer",
                                          image_error_every=5, image_error_spp=128),
                                 FILMS, {0: rgb(64, 48)})
    assert [(r.spp_field, r.spp, r.per_iteration) for r in est.renders] == [
        ("spp", 8, 2), ("image_error_spp", 128, 0)]
    assert est.samples_per_iteration == 2 * 64 * 48 * 8
    assert est.film_bytes == 64 * 48 * 16  # one film per sensor, whatever renders it


def test_render_scene_renders_the_chosen_sensors_at_their_films():
    est = admission.render_estimate(api.RenderRequest({}, 64, [1], 0), FILMS)
    assert [(r.sensor, r.width, r.height, r.spp) for r in est.renders] == [(1, 32, 32, 64)]
    every = admission.render_estimate(api.RenderRequest({}, 64, [], 0), FILMS)
    assert [r.sensor for r in every.renders] == [0, 1]
    # A sensor that does not exist is the engine's to name, not an estimate's to guess.
    assert admission.render_estimate(api.RenderRequest({}, 64, [7], 0), FILMS).renders == []


def refused(kind, fn, *args) -> str:
    with pytest.raises(kind) as err:
        fn(*args)
    return str(err.value)


def test_samples_over_the_limit_are_resource_exhausted():
    est = admission.render_estimate(api.RenderRequest({}, 1_000_000, [1], 0), FILMS)
    message = refused(ResourceExhausted, admission.check, est, Limits())
    assert "spp 1,000,000 on sensor 1's 32x32 px film is 1,024,000,000 samples" in message
    assert "the limit is 67,108,864 (matoptd --max-samples)" in message
    admission.check(est, Limits(max_samples=1_024_000_000))  # the flag raises it


def test_image_error_spp_is_named_when_it_is_the_one_over():
    est = admission.job_estimate(settings({1: "a.png"}, spp=4, image_error_every=1,
                                          image_error_spp=100_000), FILMS, {1: rgb(32, 32)})
    message = refused(ResourceExhausted, admission.check, est, Limits())
    assert message.startswith("image_error_spp 100,000 on sensor 1")


def test_2_to_the_32_samples_can_never_render():
    est = admission.render_estimate(api.RenderRequest({}, 2**31 - 1, [1], 0), FILMS)
    message = refused(InvalidArgument, admission.check, est, Limits(max_samples=1 << 40))
    assert "spp 2,147,483,647" in message and "fewer than 2^32 = 4,294,967,296" in message


def test_a_film_side_over_the_limit_is_invalid_and_says_why_it_is_that_large():
    est = admission.job_estimate(settings({0: "wide.png"}, film_height=16), FILMS,
                                 {0: rgb(100000, 1)})
    message = refused(InvalidArgument, admission.check, est, Limits())
    assert "sensor 0 would render a 1600000x16 px film" in message
    assert "reference 'wide.png' (100000x1 px)" in message
    assert "at most 8,192 px on a side (matoptd --max-film-side)" in message
    tall = admission.job_estimate(settings({1: "a.png"}, film_height=20000), FILMS,
                                  {1: rgb(32, 32)})
    message = refused(InvalidArgument, admission.check, tall, Limits())
    assert "20000x20000 px film (from film_height 20000" in message


def test_film_memory_counts_every_sensor_of_a_request():
    films = {i: (4096, 4096) for i in range(3)}
    est = admission.render_estimate(api.RenderRequest({}, 1, [], 0), films)
    message = refused(ResourceExhausted, admission.check, est, Limits(max_film_memory=512 << 20))
    assert "the films of 3 sensor(s) take 768.0 MiB" in message
    assert "(matoptd --max-film-memory)" in message
    admission.check(est, Limits())


def test_reference_pixels_and_memory_are_read_from_the_header(tmp_path):
    huge = tmp_path / "huge"
    huge.write_bytes(png_header_only(25000, 25000))
    message = refused(ResourceExhausted, admission.reference_header, huge, "huge.png", Limits())
    assert "reference image 'huge.png' is a 25000x25000 px PNG file: 625,000,000 px" in message
    assert "the limit is 67,108,864 px (matoptd --max-reference-pixels)" in message
    deep = tmp_path / "deep"
    deep.write_bytes(exr(np.zeros((64, 64, 3))))
    message = refused(ResourceExhausted, admission.reference_header, deep, "deep.exr",
                      Limits(max_reference_memory=64 * 64 * 20))
    assert "of 3 channel(s) that takes 96.0 KiB to decode" in message
    assert "(matoptd --max-reference-memory)" in message
    ok = tmp_path / "ok"
    ok.write_bytes(png(np.zeros((4, 6, 3))))
    assert admission.reference_header(ok, "ok.png", Limits()).width == 6


def test_not_an_image_is_invalid_and_named(tmp_path):
    path = tmp_path / "x"
    path.write_bytes(b"just some notes")
    message = refused(InvalidArgument, admission.reference_header, path, "notes.txt", Limits())
    assert message == ("reference image 'notes.txt' cannot be read: not a PNG, JPEG or OpenEXR "
                       "file")


def test_admit_job_reads_each_reference_by_digest(tmp_path):
    (tmp_path / "sha0").write_bytes(png(np.zeros((48, 64, 3))))
    (tmp_path / "sha1").write_bytes(png_header_only(100000, 1))
    ok = admission.admit_job(settings({0: "a.png"}, spp=16), FILMS, lambda d: tmp_path / d,
                             Limits())
    assert ok.samples_per_iteration == 64 * 48 * 16
    message = refused(InvalidArgument, admission.admit_job, settings({1: "wide.png"}), FILMS,
                      lambda d: tmp_path / d, Limits())
    assert "3200000x32 px film" in message


def test_jobs_per_user():
    admission.check_jobs("alice", 15, Limits())
    message = refused(ResourceExhausted, admission.check_jobs, "alice", 16, Limits())
    assert message.startswith("user 'alice' has 16 queued or running jobs; the limit is 16 "
                              "(matoptd --max-jobs-per-user)")


def test_task_slots_are_per_user_and_given_back():
    slots = admission.TaskSlots(Limits(max_tasks_per_user=2))
    with slots.hold("alice"), slots.hold("alice"), slots.hold("bob"):
        message = refused(ResourceExhausted, lambda: slots.hold("alice").__enter__())
        assert "user 'alice' already has 2 scene request(s)" in message
        assert "(matoptd --max-tasks-per-user)" in message
    with pytest.raises(RuntimeError):
        with slots.hold("alice"):
            raise RuntimeError("a failed task gives its slot back")
    assert not slots.held


def test_limits_refuse_nonsense_naming_the_flag():
    with pytest.raises(ValueError, match="--max-film-side must be >= 1, got 0"):
        Limits(max_film_side=0)


@pytest.mark.parametrize("spp,pixels,limit,expected", [
    (4, 64 * 64, 0, 64),                # no limit: RESULT_SPP
    (128, 64 * 64, 0, 128),             # a job's own spp when it is more
    (4, 64 * 64, 1 << 26, 64),          # well within the limit
    (4, 4096 * 4096, 1 << 26, 4),       # 64 spp would be 2^30 samples: the job's own 4
    (1, 2048 * 2048, 1 << 26, 16),      # as many as the limit allows
    (8, 8192 * 8192, 1 << 26, 8),       # never fewer than the iterations used
])
def test_results_render_within_the_sample_limit(spp, pixels, limit, expected):
    assert api.result_spp(spp, pixels, limit) == expected


def test_reference_film_follows_the_aspect_ratio():
    assert api.reference_film(48, 200, 100) == (96, 48)
    assert api.reference_film(16, 1, 100000) == (1, 16)  # never 0 px wide

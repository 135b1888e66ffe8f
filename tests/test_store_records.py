"""A job's record as status calls read it: the store keeps the latest in memory (hundreds of
GetJob calls a second cost neither SQL nor JSON), and what they read is always what was last
written, also after a restart, and never another user's."""

from __future__ import annotations

import pytest

from fakes import job as record
from matoptd.errors import NotFound
from matoptd.records import Phase
from matoptd.scheduling.state import State
from matoptd.server.convert import Converted
from matoptd.store.store import Store


def test_a_status_read_sees_each_write_and_survives_a_restart(tmp_path):
    store = Store(tmp_path)
    job = record("a", "alice")
    store.add_job(job, None)
    first = store.get_job("jobs/a", "alice")
    assert store.get_job("jobs/a") is first  # kept: the same record until the job changes

    job.phase, job.iteration, job.notes = Phase.RUNNING, 7, ["step 7"]
    store.put_job(job)
    now = store.get_job("jobs/a", "alice")
    assert (now.phase, now.iteration, now.notes) == (Phase.RUNNING, 7, ["step 7"])
    assert first.iteration == 0  # what a reader held is not changed under it
    job.iteration = 8  # the scheduler's own record changes on: the store's does not
    assert store.get_job("jobs/a").iteration == 7
    store.close()

    again = Store(tmp_path).get_job("jobs/a", "alice")
    assert (again.phase, again.iteration, again.notes) == (Phase.RUNNING, 7, ["step 7"])


def test_another_users_job_and_a_deleted_one_are_not_found(tmp_path):
    store = Store(tmp_path)
    store.add_job(record("a", "alice"), None)
    store.get_job("jobs/a", "alice")
    with pytest.raises(NotFound, match="job 'jobs/a' not found"):
        store.get_job("jobs/a", "bob")
    store.delete_job("jobs/a")
    with pytest.raises(NotFound, match="job 'jobs/a' not found"):
        store.get_job("jobs/a", "alice")


def test_the_scheduler_changes_a_copy_never_the_record_readers_share(tmp_path):
    store = Store(tmp_path)
    store.add_job(record("a", "alice"), None)
    shared = store.get_job("jobs/a")
    taken = State(store, _NoJobs()).record("jobs/a", "alice")
    taken.phase = Phase.QUEUED
    taken.notes.append("resumed")
    assert taken is not shared and shared.notes == []


def test_one_conversion_per_change_and_a_new_message_after_it(tmp_path):
    store = Store(tmp_path)
    job = record("a", "alice")
    store.add_job(job, None)
    converted = Converted()
    before = converted.job(store.get_job("jobs/a"))
    assert converted.job(store.get_job("jobs/a")) is before
    job.iteration = 3
    store.put_job(job)
    after = converted.job(store.get_job("jobs/a"))
    assert (before.iteration, after.iteration) == (0, 3)


class _NoJobs:
    jobs: dict = {}

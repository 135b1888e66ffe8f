"""Shell completion of scene, job and blob names, asked of the daemon.

Click completes commands and options by itself; the names of a user's scenes and jobs only
the daemon knows. A shell waits for the answer while the user waits for the shell, so the
daemon gets a short deadline, and any failure (no daemon, a wrong token, a slow network)
completes nothing rather than print an error into the command line being typed.
"""

from __future__ import annotations

from functools import partial
from typing import Callable

import click
from click.shell_completion import CompletionItem

from matopt_client import client as mc
from matopt_client.cli.session import completion_settings
from matopt_api.v1 import matopt_pb2 as pb

TIMEOUT_S = 1.0  # per call: long enough for a daemon on the LAN, short enough to type on
PAGE_SIZE = 1000  # the most a page holds: one call for nearly everyone


def _scenes(client: mc.Client) -> list[tuple[str, str]]:
    scenes = mc.list_all(partial(client.scenes.ListScenes, timeout=TIMEOUT_S),
                         pb.ListScenesRequest(page_size=PAGE_SIZE), "scenes")
    return [(s.name, s.display_name) for s in scenes]


def _jobs(client: mc.Client) -> list[tuple[str, str]]:
    jobs = mc.list_all(partial(client.jobs.ListJobs, timeout=TIMEOUT_S),
                       pb.ListJobsRequest(page_size=PAGE_SIZE), "jobs")
    return [(j.name, f"{mc.state_name(j.state)} {j.iteration}/{j.spec.iterations}")
            for j in jobs]


def _blobs(client: mc.Client) -> list[tuple[str, str]]:
    blobs = client.blobs.ListBlobs(pb.ListBlobsRequest(), timeout=TIMEOUT_S).blobs
    return [(b.name, ", ".join(b.used_by) or "unused") for b in blobs]


LISTERS: dict[str, Callable[[mc.Client], list[tuple[str, str]]]] = {
    "scenes": _scenes, "jobs": _jobs, "blobs": _blobs}


def names(collection: str, ctx: click.Context, incomplete: str) -> list[CompletionItem]:
    """The caller's ``collection`` names that start with ``incomplete``, newest last, each
    with what it is (state, display name) for shells that show it (zsh, fish).

    Bare ids unless the user started typing a full name (``jobs/``), as both are accepted.
    """
    settings = completion_settings(ctx)
    try:
        with mc.connect(settings.server, settings.token, settings.tls_ca,
                        probe_timeout=TIMEOUT_S) as client:
            found = LISTERS[collection](client)
    except Exception:  # noqa: BLE001 - nothing to complete, never an error in the shell
        return []
    full = "/" in incomplete
    return [CompletionItem(name if full else name.removeprefix(f"{collection}/"), help=about)
            for name, about in found
            if (name if full else name.removeprefix(f"{collection}/")).startswith(incomplete)]

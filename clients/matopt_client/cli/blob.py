"""``matopt blob ...``: your files on the daemon (uploads, renders, results), how much of your
quota they take, and deleting those nothing uses any more."""

from __future__ import annotations

import click

from matopt_client import client as mc
from matopt_client.cli.output import deleted, emit_json, json_option, note, size, table
from matopt_client.cli.params import BLOB
from matopt_client.cli.session import Group, connected
from matopt_api.v1 import matopt_pb2 as pb


@click.group(cls=Group)
def blob() -> None:
    """List and delete your blobs: uploaded files, renders and results."""


def _listing(client: mc.Client) -> pb.ListBlobsResponse:
    """Every page; the usage and quota are the same on each."""
    request = pb.ListBlobsRequest()
    out = pb.ListBlobsResponse()
    while True:
        page = client.blobs.ListBlobs(request)
        out.blobs.extend(page.blobs)
        out.used_bytes, out.quota_bytes = page.used_bytes, page.quota_bytes
        if not page.next_page_token:
            return out
        request.page_token = page.next_page_token


@blob.command("list")
@json_option
def list_blobs(as_json: bool) -> None:
    """List your blobs, the scenes and jobs that use them, and your usage against the quota."""
    listing = _listing(connected())
    if as_json:
        emit_json(listing)
        return
    table(["NAME", "SIZE", "USED BY"],
          [[b.name, size(b.size_bytes), ", ".join(b.used_by)] for b in listing.blobs])
    quota = f"of your quota of {size(listing.quota_bytes)}" if listing.quota_bytes else \
        "(no quota)"
    note(f"{len(listing.blobs)} blob(s), {size(listing.used_bytes)} {quota}")


@blob.command("rm")
@click.argument("names", metavar="BLOB...", nargs=-1, type=BLOB)
@click.option("--unused", is_flag=True, help="every blob of yours that no scene or job uses")
@json_option
def remove(names: tuple[str, ...], unused: bool, as_json: bool) -> None:
    """Delete blobs (blobs/<sha256> or the bare digest).

    A blob that one of your scenes or jobs uses is refused, naming them: delete those first.
    The content leaves the daemon's disk once no user has it.
    """
    if not names and not unused:
        raise click.UsageError("name a BLOB to delete, or give --unused")
    client = connected()
    if unused:
        names += tuple(b.name for b in _listing(client).blobs
                       if not b.used_by and b.name not in names)
    done: list[str] = []
    try:
        for name in names:
            client.blobs.DeleteBlob(pb.DeleteBlobRequest(name=name))
            done.append(name)
    finally:  # those deleted before a refusal are gone: said on stderr, not as JSON
        deleted(done, as_json and len(done) == len(names))

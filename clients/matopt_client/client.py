"""The client library shared by the CLI, the Qt app and scripts: one gRPC connection to matoptd.

Everything here speaks the v1 API only (``matopt_api.v1``); nothing imports mitsuba, drjit or the
daemon package, so a client machine needs no renderer. Plain functions take a :class:`Client`
instead of hiding state in objects, so a caller can use the stubs directly for anything this
module does not wrap.
"""

from __future__ import annotations

import hashlib
import json
import os
import posixpath
import re
import struct
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Iterator, NamedTuple, Sequence

import grpc

from matopt_api import bundle, enums
from matopt_api.v1 import matopt_pb2 as pb
from matopt_api.v1 import matopt_pb2_grpc as rpc

from . import scene_files

DEFAULT_PORT = 50051  # matoptd's, for an address given without one
DEFAULT_SERVER = f"127.0.0.1:{DEFAULT_PORT}"  # where matoptd listens unless told otherwise
GRPC_SCHEMES = ("unix:", "unix-abstract:", "vsock:", "dns:", "ipv4:", "ipv6:")
MAX_MESSAGE_BYTES = 64 * 1024 * 1024
CHUNK_BYTES = 1024 * 1024  # the API's chunk limit for blob streams
PROBE_TIMEOUT_S = 5.0  # the first call: long enough for a remote daemon, short enough to wait out
# gRPC's own retries (a service config): a call refused for a moment (RESOURCE_EXHAUSTED: too
# many of one's requests in progress; UNAVAILABLE: the daemon restarting) goes again, after
# the delay the daemon names (grpc-retry-pushback-ms, with its google.rpc.RetryInfo) or after
# an exponential backoff, at most 5 attempts in all (gRPC's cap). A limit that retrying does
# not lift comes with a pushback of -1 and is not retried. Streams of blob chunks are retried
# only while they fit gRPC's retry buffer (256 KiB), the first chunk of an upload included.
# ServerService is left out: GetServerInfo meets no limit, and the first call of a connection
# (``probe``) should say at once that no daemon answers at an address.
RETRY_POLICY = {
    "maxAttempts": 5,
    "initialBackoff": "0.2s",
    "maxBackoff": "5s",
    "backoffMultiplier": 2,
    "retryableStatusCodes": ["RESOURCE_EXHAUSTED", "UNAVAILABLE"],
}
SERVICE_CONFIG = json.dumps({"methodConfig": [{
    "name": [{"service": f"matopt.v1.{s}"} for s in
             ("BlobService", "SceneService", "JobService")],
    "retryPolicy": RETRY_POLICY}]})

# States after which a job changes no more (INTERRUPTED may still be resumed, but no longer runs).
TERMINAL_STATES = frozenset({pb.JOB_STATE_SUCCEEDED, pb.JOB_STATE_FAILED, pb.JOB_STATE_CANCELLED})


class ClientError(Exception):
    """A failure on the client side whose message is already fit to show the user as is."""


class Unreachable(ClientError):
    """No matoptd answers at the address: distinct from an error the daemon itself returned."""


class LocalFileError(ClientError):
    """A file on this machine is missing, unreadable or not a valid scene: the user's to fix
    before asking the daemon anything (the CLI exits 2 for it, as for a usage error)."""


# ---------------------------------------------------------------------------------------------
# Connection
# ---------------------------------------------------------------------------------------------


@dataclass
class Client:
    """An open channel to one matoptd and a stub per service; close it (or use ``with``)."""

    target: str
    channel: grpc.Channel
    blobs: rpc.BlobServiceStub = field(init=False)
    scenes: rpc.SceneServiceStub = field(init=False)
    jobs: rpc.JobServiceStub = field(init=False)
    server: rpc.ServerServiceStub = field(init=False)
    info: pb.ServerInfo | None = None  # from the first call, when connect() made one

    def __post_init__(self) -> None:
        self.blobs = rpc.BlobServiceStub(self.channel)
        self.scenes = rpc.SceneServiceStub(self.channel)
        self.jobs = rpc.JobServiceStub(self.channel)
        self.server = rpc.ServerServiceStub(self.channel)

    def close(self) -> None:
        self.channel.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class _CallDetails(NamedTuple):
    method: str
    timeout: float | None
    metadata: Sequence[tuple[str, str]] | None
    credentials: grpc.CallCredentials | None
    wait_for_ready: bool | None
    compression: grpc.Compression | None


class _BearerToken(
    grpc.UnaryUnaryClientInterceptor,
    grpc.UnaryStreamClientInterceptor,
    grpc.StreamUnaryClientInterceptor,
    grpc.StreamStreamClientInterceptor,
):
    """Adds ``authorization: Bearer <token>`` to every call on a plaintext channel.

    gRPC only attaches call credentials to secure channels, so without TLS the token has to
    travel as plain metadata, which is what the daemon reads in both cases.
    """

    def __init__(self, token: str) -> None:
        self._header = ("authorization", f"Bearer {token}")

    def _details(self, details: grpc.ClientCallDetails) -> _CallDetails:
        metadata = [*(details.metadata or ()), self._header]
        return _CallDetails(details.method, details.timeout, metadata, details.credentials,
                            getattr(details, "wait_for_ready", None),
                            getattr(details, "compression", None))

    def intercept_unary_unary(self, continuation, details, request):
        return continuation(self._details(details), request)

    def intercept_unary_stream(self, continuation, details, request):
        return continuation(self._details(details), request)

    def intercept_stream_unary(self, continuation, details, request_iterator):
        return continuation(self._details(details), request_iterator)

    def intercept_stream_stream(self, continuation, details, request_iterator):
        return continuation(self._details(details), request_iterator)


def with_port(server: str) -> str:
    """``gpu-box`` -> ``gpu-box:50051``: an address without a port gets matoptd's (gRPC's
    own default would be 443). Addresses with a scheme (``unix:/run/m.sock``, ``dns:///h``)
    are gRPC's to read and stay as given."""
    if server.startswith(GRPC_SCHEMES):
        return server
    if server.startswith("["):  # [::1] or [::1]:50051
        return server if re.search(r"\]:\d+$", server) else f"{server}:{DEFAULT_PORT}"
    if server.count(":") > 1:  # a bare IPv6 address
        return f"[{server}]:{DEFAULT_PORT}"
    return server if ":" in server else f"{server}:{DEFAULT_PORT}"


def connect(server: str, token: str | None = None, tls_ca: str | None = None, *,
            probe_timeout: float | None = PROBE_TIMEOUT_S) -> Client:
    """Opens a channel to matoptd at ``server`` ("host:port"; without a port, matoptd's
    50051) and checks that it answers.

    gRPC connects lazily and a call to a dead address fails with an opaque UNAVAILABLE, so the
    first call (GetServerInfo, kept in ``Client.info``) runs here under a short deadline and a
    failure becomes :class:`Unreachable` naming the address. ``probe_timeout=None`` skips it,
    for a caller (a GUI) that must not block. Errors the daemon returns (UNAUTHENTICATED, ...)
    propagate as ``grpc.RpcError``.
    """
    server = with_port(server)
    options = [
        ("grpc.max_send_message_length", MAX_MESSAGE_BYTES),
        ("grpc.max_receive_message_length", MAX_MESSAGE_BYTES),
        ("grpc.enable_retries", 1),
        ("grpc.service_config", SERVICE_CONFIG),
    ]
    if tls_ca:
        try:
            root = Path(tls_ca).read_bytes()
        except OSError as exc:
            raise LocalFileError(f"cannot read the TLS CA certificate '{tls_ca}': "
                              f"{exc.strerror or exc}") from None
        creds = grpc.ssl_channel_credentials(root_certificates=root)
        if token:
            creds = grpc.composite_channel_credentials(
                creds, grpc.access_token_call_credentials(token))
        channel = grpc.secure_channel(server, creds, options=options)
    else:
        channel = grpc.insecure_channel(server, options=options)
        if token:
            channel = grpc.intercept_channel(channel, _BearerToken(token))
    client = Client(server, channel)
    if probe_timeout is not None:
        try:
            client.info = probe(client, probe_timeout)
        except BaseException:
            client.close()
            raise
    return client


def probe(client: Client, timeout: float = PROBE_TIMEOUT_S) -> pb.ServerInfo:
    """GetServerInfo under a short deadline; a transport failure becomes :class:`Unreachable`."""
    try:
        return client.server.GetServerInfo(pb.GetServerInfoRequest(), timeout=timeout)
    except grpc.RpcError as exc:
        code = exc.code() if hasattr(exc, "code") else None
        if code == grpc.StatusCode.UNAVAILABLE:
            raise Unreachable(f"cannot reach matoptd at {client.target}: "
                              f"{_one_line(exc.details())}") from None
        if code == grpc.StatusCode.DEADLINE_EXCEEDED:
            raise Unreachable(f"cannot reach matoptd at {client.target}: "
                              f"no answer within {timeout:g} s") from None
        raise


def error_message(exc: grpc.RpcError) -> str:
    """One line for the user: ``"<CODE>: <details>"``, e.g. ``NOT_FOUND: job 'jobs/x' not found``.

    The daemon's details already name the file, key or value at fault; only the code is added.
    """
    code = exc.code() if hasattr(exc, "code") else None
    details = exc.details() if hasattr(exc, "details") else None
    name = code.name if code is not None else "UNKNOWN"
    return f"{name}: {_one_line(details or str(exc))}"


def _one_line(text: str | None) -> str:
    return " ".join((text or "").split())


# ---------------------------------------------------------------------------------------------
# Names and values
# ---------------------------------------------------------------------------------------------


def resource_name(collection: str, name: str) -> str:
    """``"jobs", "abc"`` -> ``"jobs/abc"``; a name that already has a collection is kept.

    Users type the bare id they see in listings; the API wants full names.
    """
    return name if "/" in name else f"{collection}/{name}"


def blob_name(sha256: str) -> str:
    return resource_name("blobs", sha256)


def short_float(value: float) -> float:
    """The shortest decimal that reads back as the same float32, e.g. 0.57 not 0.5699999928.

    Parameter values travel as float32; printing them as doubles shows noise digits.
    """
    try:
        single = struct.unpack("<f", struct.pack("<f", value))[0]
    except (OverflowError, struct.error):
        return value
    if single != single or single in (float("inf"), float("-inf")):
        return single
    for digits in range(1, 10):
        candidate = float(f"{single:.{digits}g}")
        if struct.unpack("<f", struct.pack("<f", candidate))[0] == single:
            return candidate
    return single


def short_floats(values: Iterable[float]) -> list[float]:
    return [short_float(v) for v in values]


# ---------------------------------------------------------------------------------------------
# Blobs
# ---------------------------------------------------------------------------------------------

UploadProgress = Callable[[str, int], None]  # (file being uploaded, its size in bytes)


def sha256_file(path: str | os.PathLike) -> str:
    """The lowercase hex digest that names the file's blob."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(CHUNK_BYTES):
            digest.update(chunk)
    return digest.hexdigest()


def _upload_chunks(path: Path, sha256: str, size: int) -> Iterator[pb.UploadBlobRequest]:
    yield pb.UploadBlobRequest(header=pb.UploadBlobRequest.Header(sha256=sha256, size_bytes=size))
    with open(path, "rb") as f:
        while chunk := f.read(CHUNK_BYTES):
            yield pb.UploadBlobRequest(chunk=chunk)


def upload_files(client: Client, paths: Sequence[str | os.PathLike],
                 on_upload: UploadProgress | None = None,
                 labels: Sequence[str] | None = None) -> list[str]:
    """Makes sure the server has every file's content; returns their sha256 digests, in order.

    One FindMissingBlobs call covers all files, so content the server already has (a scene
    loaded before, a shared texture) is not sent again. ``labels`` name the files for
    ``on_upload`` (default: their paths).
    """
    files = [Path(p) for p in paths]
    digests: list[str] = []
    for p in files:
        try:
            digests.append(sha256_file(p))
        except OSError as exc:
            raise LocalFileError(f"cannot read '{p}': {exc.strerror or exc}") from None
    unique = list(dict.fromkeys(digests))
    if not unique:
        return []
    missing = set(client.blobs.FindMissingBlobs(
        pb.FindMissingBlobsRequest(sha256=unique)).missing_sha256)
    for p, sha, label in zip(files, digests, labels or [str(p) for p in files]):
        if sha not in missing:
            continue
        missing.discard(sha)
        size = p.stat().st_size
        if on_upload:
            on_upload(label, size)
        client.blobs.UploadBlob(_upload_chunks(p, sha, size))
    return digests


def upload_file(client: Client, path: str | os.PathLike,
                on_upload: UploadProgress | None = None) -> str:
    """Uploads one file (unless the server has it) and returns its sha256."""
    return upload_files(client, [path], on_upload)[0]


def bundle_files(main_xml_path: str | os.PathLike, overrides: dict[str, str] | None = None,
                 root: str | os.PathLike | None = None) -> tuple[str, dict[str, Path]]:
    """The bundle of a scene on disk: its main file's bundle path and every file it needs.

    Files are found by the daemon's rules (``matopt_api.bundle``: includes, meshes, textures,
    spectra, ...) from the bundle's root: ``root`` (the folder the scene's file names are
    relative to), else the first folder under which every file is found (``scene_files``).
    Missing files are reported here, all at once, rather than by the daemon after an upload.
    """
    try:
        return scene_files.find_bundle(main_xml_path, overrides, root)
    except (scene_files.SceneFilesError, bundle.BundleError) as exc:
        raise LocalFileError(str(exc)) from None


def upload_bundle(client: Client, main_xml_path: str | os.PathLike,
                  overrides: dict[str, str] | None = None,
                  on_upload: UploadProgress | None = None,
                  root: str | os.PathLike | None = None) -> tuple[str, list[pb.BundleFile]]:
    """Uploads a scene's bundle; returns what CreateScene needs: main_file and the files.

    ``overrides`` are the XML defaults the scene will be created with: a ``$name`` in a
    filename may select a different file than the XML's default. ``root``: as for
    ``bundle_files``.
    """
    main_file, files = bundle_files(main_xml_path, overrides, root)
    paths = sorted(files)
    digests = upload_files(client, [files[p] for p in paths], on_upload, labels=paths)
    return main_file, [pb.BundleFile(path=p, sha256=d) for p, d in zip(paths, digests)]


def download_blob(client: Client, name: str, dest_path: str | os.PathLike) -> Path:
    """Writes blob ``name`` ("blobs/<sha256>" or the bare digest) to ``dest_path``.

    The file appears only once complete and verified, so an interrupted download never leaves
    a truncated image behind that looks like a result.
    """
    name = blob_name(name)
    dest = Path(dest_path)
    dest.parent.mkdir(parents=True, exist_ok=True)
    digest = hashlib.sha256()
    tmp = dest.with_name(f".{dest.name}.{uuid.uuid4().hex[:8]}.part")  # mode as umask says
    try:
        with open(tmp, "xb") as f:
            for part in client.blobs.DownloadBlob(pb.DownloadBlobRequest(name=name)):
                digest.update(part.chunk)
                f.write(part.chunk)
        expected = posixpath.basename(name)
        if digest.hexdigest() != expected:
            raise ClientError(f"download of {name} is corrupt (got sha256 {digest.hexdigest()})")
        os.replace(tmp, dest)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return dest


# ---------------------------------------------------------------------------------------------
# Jobs
# ---------------------------------------------------------------------------------------------


def watch(client: Client, job_name: str) -> Iterator[pb.JobEvent]:
    """The job's events as they happen: the job first, then one per iteration, until it ends.

    Closing the generator (or leaving a ``for`` loop early) cancels the stream on the server.
    """
    call = client.jobs.WatchJob(pb.WatchJobRequest(name=resource_name("jobs", job_name)))
    try:
        yield from call
    finally:
        call.cancel()


def wait(client: Client, job_name: str,
         on_event: Callable[[pb.JobEvent], None] | None = None) -> pb.Job:
    """Blocks until the job ends and returns it in its final state.

    If the stream ends without a final state (the daemon stopped), the job is fetched once
    more, so the caller sees e.g. INTERRUPTED instead of a stale RUNNING.
    """
    name = resource_name("jobs", job_name)
    last: pb.Job | None = None
    for event in watch(client, name):
        if on_event:
            on_event(event)
        if event.HasField("job"):
            last = event.job
    if last is None or last.state not in TERMINAL_STATES:
        last = client.jobs.GetJob(pb.GetJobRequest(name=name))
    return last


def state_name(state: int) -> str:
    """"RUNNING" for JOB_STATE_RUNNING."""
    return enums.short_name(pb.JobState, state)


def list_all(method: Callable, request, field_name: str) -> list:
    """Every item of a paged call (ListScenes, ListJobs, GetJobHistory), following
    next_page_token."""
    items: list = []
    while True:
        response = method(request)
        items.extend(getattr(response, field_name))
        if not response.next_page_token:
            return items
        request.page_token = response.next_page_token


def job_history(client: Client, name: str) -> list[pb.IterationRecord]:
    """Every iteration a job recorded, across GetJobHistory's pages."""
    return list_all(client.jobs.GetJobHistory, pb.GetJobHistoryRequest(name=name), "iterations")

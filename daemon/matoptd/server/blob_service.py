"""BlobService: content-addressed uploads and downloads, each user's own (``store/blobs.py``)."""

from __future__ import annotations

from google.protobuf import empty_pb2

from matopt_api.v1 import matopt_pb2 as pb
from matopt_api.v1 import matopt_pb2_grpc as rpc

from ..errors import InvalidArgument
from ..store.store import CHUNK
from .backend import Backend
from .convert import blob_to_pb
from .interceptors import caller
from .paging import next_token, page, resource


class BlobService(rpc.BlobServiceServicer):
    def __init__(self, backend: Backend) -> None:
        self.blobs = backend.store.blobs

    async def FindMissingBlobs(self, request, context):
        user = caller()
        return pb.FindMissingBlobsResponse(
            missing_sha256=[s for s in request.sha256 if not self.blobs.owns(user, s)])

    async def UploadBlob(self, request_iterator, context):
        user = caller()
        upload = self.blobs.begin_upload(user)
        try:
            header = None
            async for msg in request_iterator:
                if msg.HasField("header"):
                    if header is not None:
                        raise InvalidArgument("UploadBlob got a second header")
                    header = msg.header
                    self.blobs.path(header.sha256)  # validates the digest's form
                    # Refused before the content travels; checked again when it is kept.
                    self.blobs.check_room(user, header.size_bytes, header.sha256)
                elif header is None:
                    raise InvalidArgument("UploadBlob must start with a header "
                                          "(sha256, size_bytes)")
                else:
                    upload.write(msg.chunk)
            if header is None:
                raise InvalidArgument("UploadBlob got no header")
            sha, size = upload.commit(header.sha256, header.size_bytes, within_quota=True)
            return pb.Blob(name=f"blobs/{sha}", sha256=sha, size_bytes=size)
        finally:
            upload.abort()

    async def DownloadBlob(self, request, context):
        path = self.blobs.file(request.name, caller())
        with open(path, "rb") as f:
            while chunk := f.read(CHUNK):
                yield pb.DownloadBlobResponse(chunk=chunk)

    async def ListBlobs(self, request, context):
        user = caller()
        offset, limit = page(request.page_token, request.page_size)
        found = self.blobs.list(user, offset, limit)
        return pb.ListBlobsResponse(blobs=[blob_to_pb(b) for b in found],
                                    next_page_token=next_token(offset, limit, len(found)),
                                    used_bytes=self.blobs.usage(user),
                                    quota_bytes=self.blobs.quota or 0)

    async def DeleteBlob(self, request, context):
        self.blobs.delete(caller(), resource("blobs", request.name))
        return empty_pb2.Empty()

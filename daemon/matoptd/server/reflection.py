"""Server reflection under both names: ``grpc.reflection.v1`` and ``v1alpha``.

grpcio-reflection implements only v1alpha, but newer tools (buf curl, grpcurl >= 1.9, Postman)
ask for v1 first. The two services carry the same messages under another package name, so the
bytes on the wire are identical and one servicer can answer both; the v1 file is the v1alpha
one renamed, so that reflection can describe itself under either name too.
"""

from __future__ import annotations

import grpc
from google.protobuf import descriptor_pb2, descriptor_pool, text_format
from grpc_reflection.v1alpha import reflection, reflection_pb2

V1_SERVICE = "grpc.reflection.v1.ServerReflection"


def _register_v1() -> None:
    """Adds grpc/reflection/v1/reflection.proto to the default pool (once)."""
    pool = descriptor_pool.Default()
    try:
        pool.FindServiceByName(V1_SERVICE)
        return
    except KeyError:
        pass
    file = descriptor_pb2.FileDescriptorProto()
    reflection_pb2.DESCRIPTOR.CopyToProto(file)
    text = text_format.MessageToString(file).replace("grpc.reflection.v1alpha",
                                                     "grpc.reflection.v1")
    file = text_format.Parse(text, descriptor_pb2.FileDescriptorProto())
    file.name = "grpc/reflection/v1/reflection.proto"
    pool.Add(file)


def enable(server: grpc.aio.Server, service_names: list[str]) -> None:
    """Serves reflection for ``service_names`` (and itself) under both names."""
    _register_v1()
    servicer = reflection.aio.ReflectionServicer(
        [*service_names, reflection.SERVICE_NAME, V1_SERVICE])
    handler = grpc.stream_stream_rpc_method_handler(
        servicer.ServerReflectionInfo,
        request_deserializer=reflection_pb2.ServerReflectionRequest.FromString,
        response_serializer=reflection_pb2.ServerReflectionResponse.SerializeToString)
    for name in (reflection.SERVICE_NAME, V1_SERVICE):
        server.add_generic_rpc_handlers((grpc.method_handlers_generic_handler(
            name, {"ServerReflectionInfo": handler}),))

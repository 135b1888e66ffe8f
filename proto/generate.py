"""Generates the Python gRPC stubs from the .proto files: the one place this happens.

Run by the build (setup.py) and by hand after editing a .proto:

    python proto/generate.py

The stubs land in ``proto/matopt_api/v1/`` (the import package ``matopt_api.v1``, the contract
that both the daemon and the clients import, shipped with the base distribution), next to a
copy of the .proto files, which are the public contract for clients in other languages. The
.proto keeps its canonical path ``matopt/v1/matopt.proto`` (package ``matopt.v1``), so the
one import protoc writes for that path is pointed at ``matopt_api.v1``.
"""

from __future__ import annotations

import shutil
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PROTO_ROOT = ROOT / "proto"
PACKAGE = Path("matopt") / "v1"
OUT = ROOT / "proto" / "matopt_api" / "v1"


def generate(out: Path = OUT) -> list[Path]:
    """Compiles every .proto under proto/matopt/v1 into ``out`` and returns the files written."""
    from grpc_tools import protoc  # build-time dependency only
    import grpc_tools

    protos = sorted((PROTO_ROOT / PACKAGE).glob("*.proto"))
    include = Path(grpc_tools.__file__).parent / "_proto"  # google/protobuf/*.proto
    with tempfile.TemporaryDirectory() as tmp:
        args = [
            "protoc",
            f"-I{PROTO_ROOT}",
            f"-I{include}",
            f"--python_out={tmp}",
            f"--pyi_out={tmp}",
            f"--grpc_python_out={tmp}",
            *[str(p) for p in protos],
        ]
        if protoc.main(args) != 0:
            raise RuntimeError(f"protoc failed on {[p.name for p in protos]}")
        out.mkdir(parents=True, exist_ok=True)
        written = []
        for f in sorted((Path(tmp) / PACKAGE).iterdir()):
            text = f.read_text().replace("from matopt.v1 import", "from matopt_api.v1 import")
            (out / f.name).write_text(text)
            written.append(out / f.name)
    for p in protos:
        shutil.copy2(p, out / p.name)
        written.append(out / p.name)
    init = out / "__init__.py"
    init.write_text('"""Generated from proto/matopt/v1 by proto/generate.py. Do not edit."""\n')
    written.append(init)
    return written


if __name__ == "__main__":
    for path in generate(Path(sys.argv[1]) if len(sys.argv) > 1 else OUT):
        print(path.relative_to(ROOT) if path.is_relative_to(ROOT) else path)

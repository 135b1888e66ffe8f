"""matoptd: the daemon that owns the GPU and Dr.Jit and serves the matopt v1 gRPC API.

Two kinds of process. The server (``main``) never imports Mitsuba or Dr.Jit: ``server/`` is the
API's edge (gRPC, protobuf <-> plain data, who is calling, admission), ``scheduling/`` decides
and carries out who runs what, ``store/`` keeps what survives a restart. Workers
(``workers/``: processes or Ray actors, one engine each) run ``engine/``, the only code that
imports Mitsuba and Dr.Jit, behind the one interface ``engine_api``.

Shared by both, pure data: ``settings`` (what a job is asked to do, every default declared
once), ``engine_api``, ``truth`` and ``range_notes``; the server's own: ``records`` (a job's
record and phase, scenes, results) and ``errors`` (failures in the daemon's terms).
"""

from matopt_api import __version__

__all__ = ["__version__"]

"""matoptd: the daemon that owns the GPU and Dr.Jit and serves the matopt v1 gRPC API.

This process (``main``, ``server``: the gRPC handlers; ``store``: what survives a restart;
``scheduler``: who runs what next; ``runner``: carrying it out) never imports Mitsuba or Dr.Jit.
Renderer worker processes (``worker``, supervised by ``workers``) run the ``engine``, the only
code that does, behind the one interface ``engine_api``.
"""

from matopt_api import __version__

__all__ = ["__version__"]

"""matoptd: the daemon that owns the GPU and Dr.Jit and serves the matopt v1 gRPC API.

Layers: ``server`` (gRPC handlers, no Dr.Jit) -> ``scheduler`` (the one worker thread that
runs engine work, jobs taking turns) -> ``engine`` (the only code that imports mitsuba and
drjit). ``store`` keeps everything that must survive a restart.
"""

from matopt_api import __version__

__all__ = ["__version__"]

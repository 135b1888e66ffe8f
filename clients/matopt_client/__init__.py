"""matopt_client: the clients of the material-reconstruction daemon (``matoptd``): the
``matopt`` command, ``matopt-qt`` and the client library scripts import.

This package never imports mitsuba or drjit: the CLI, the Qt app and scripts only speak the
v1 gRPC API through the contract package ``matopt_api`` (stubs generated from ``proto/``).
"""

from matopt_api import __version__

__all__ = ["__version__"]

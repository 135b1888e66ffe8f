"""matopt: clients of the material-reconstruction daemon (``matoptd``).

This package never imports mitsuba or drjit: the CLI, the Qt app and scripts only speak the
v1 gRPC API (``matopt.v1``, generated from ``proto/``).
"""

__version__ = "0.1.0"

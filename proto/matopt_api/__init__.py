"""matopt_api: the contract between matoptd and its clients.

``matopt_api.v1`` holds the gRPC stubs generated from ``proto/matopt/v1/matopt.proto`` (by
``proto/generate.py``) and a copy of that file; ``matopt_api.bundle`` holds the rules of a
scene bundle (which files an XML references, which paths are legal) that the client applies
before an upload and the daemon applies again after it. Both sides import this package; it
imports neither of them.
"""

__version__ = "0.1.0"

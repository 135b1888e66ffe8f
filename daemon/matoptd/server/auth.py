"""Who is calling: bearer tokens mapped to user names.

With a tokens file every RPC (but health and reflection, which are separate services) needs
``authorization: Bearer <token>`` (``interceptors.Authentication`` asks). Without one the daemon
serves a single local user and binds loopback only, so nobody else can reach it.
"""

from __future__ import annotations

import hmac
from pathlib import Path
from typing import Iterable

LOCAL_USER = "local"
MIN_TOKEN_LENGTH = 16


def load_tokens(path: Path) -> dict[str, str]:
    """Parses ``TOKEN USER`` lines; '#' starts a comment. Errors name the file and line."""
    tokens: dict[str, str] = {}
    for n, line in enumerate(Path(path).read_text().splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.split()
        if len(parts) != 2:
            raise ValueError(f"{path}:{n}: expected 'TOKEN USER', got {len(parts)} fields")
        token, user = parts
        if len(token) < MIN_TOKEN_LENGTH:
            raise ValueError(f"{path}:{n}: token for '{user}' is shorter than "
                             f"{MIN_TOKEN_LENGTH} characters")
        if token in tokens:
            raise ValueError(f"{path}:{n}: the same token appears twice")
        tokens[token] = user
    if not tokens:
        raise ValueError(f"{path}: no tokens")
    return tokens


class Authenticator:
    def __init__(self, tokens: dict[str, str] | None) -> None:
        self.tokens = tokens

    def user(self, metadata: Iterable[tuple[str, str]] | None) -> str | None:
        """The calling user by a call's metadata, or None when the token is missing or
        unknown."""
        if self.tokens is None:
            return LOCAL_USER
        header = dict(metadata or ()).get("authorization", "")
        scheme, _, token = header.partition(" ")
        if scheme.lower() != "bearer" or not token:
            return None
        for known, user in self.tokens.items():
            if hmac.compare_digest(known.encode(), token.strip().encode()):
                return user
        return None

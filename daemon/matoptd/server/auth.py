"""Who is calling: bearer tokens mapped to user names.

With a tokens file every RPC (but health and reflection, which are separate services) needs
``authorization: Bearer <token>`` (``interceptors.Authentication`` asks). Without one the daemon
serves a single local user and binds loopback only, so nobody else can reach it.

The table is read again on SIGHUP (``Authenticator.reload``) and replaced whole, in one
assignment: a call sees the old table or the new one, never half of each, and nothing else
(jobs, streams, connections) is touched. A file that cannot be used keeps the old table.
"""

from __future__ import annotations

import hmac
import logging
from pathlib import Path
from typing import Iterable

log = logging.getLogger("matoptd.auth")

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
    """``tokens`` None: the local user only. ``path``: the file ``reload`` reads."""

    def __init__(self, tokens: dict[str, str] | None, path: Path | None = None) -> None:
        self.tokens, self.path = tokens, path

    @classmethod
    def from_file(cls, path: Path) -> Authenticator:
        """OSError or ValueError (naming the file and line) when it cannot be used."""
        return cls(load_tokens(path), Path(path))

    @property
    def users(self) -> set[str]:
        return set((self.tokens or {}).values())

    def reload(self) -> bool:
        """Reads the file again and swaps the table in; on a bad file logs why and keeps the
        old one. True when the new table is in use."""
        if self.path is None:
            log.warning("SIGHUP: no --tokens file to read again (only the local user is "
                        "served)")
            return False
        try:
            tokens = load_tokens(self.path)
        except (OSError, ValueError) as exc:
            log.error("tokens not reloaded, the previous ones stay in use: %s", exc)
            return False
        before = self.users
        self.tokens = tokens  # one assignment: calls in flight keep the table they read
        after = self.users
        log.info("tokens reloaded from %s: %d user(s)%s%s", self.path, len(after),
                 f"; added {', '.join(sorted(after - before))}" if after - before else "",
                 f"; removed {', '.join(sorted(before - after))}" if before - after else "")
        return True

    def user(self, metadata: Iterable[tuple[str, str]] | None) -> str | None:
        """The calling user by a call's metadata, or None when the token is missing or
        unknown."""
        tokens = self.tokens  # this call's table, whatever a reload does meanwhile
        if tokens is None:
            return LOCAL_USER
        header = dict(metadata or ()).get("authorization", "")
        scheme, _, token = header.partition(" ")
        if scheme.lower() != "bearer" or not token:
            return None
        for known, user in tokens.items():
            if hmac.compare_digest(known.encode(), token.strip().encode()):
                return user
        return None

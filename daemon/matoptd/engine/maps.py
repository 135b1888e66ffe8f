"""The chain of maps between Adam's variable u and the value v the scene renders, as the
choices in force contribute them, each for its own keys (choices/base.py):

    u_0 = encode(v_0)           (reversed: the last map first)
    v = decode(expand(u))       u clipped to bounds(lo, hi)   rate = rate(base)
"""

from __future__ import annotations

import numpy as np

from .choices import Choice, overrides
from .diagnosis import Kept
from .records import ParamRecord


class Maps:
    def __init__(self, active: list[Choice]) -> None:
        self.active = active
        # per (hook, key), looked up at every update; kept here, not in a functools cache,
        # which would hold every job's choices (and their buffers) for the process's life
        self._chains: dict[tuple[str, str], tuple[Choice, ...]] = {}

    def chain(self, hook: str, key: str) -> tuple[Choice, ...]:
        """The choices in force whose ``hook`` acts on ``key``, in registry order."""
        found = self._chains.get((hook, key))
        if found is None:
            found = self._chains[hook, key] = tuple(
                c for c in self.active if key in c.keys and overrides(c, hook))
        return found

    def encode(self, key: str, value: np.ndarray) -> np.ndarray:
        for c in reversed(self.chain("encode", key)):
            value = c.encode(key, value)
        return value

    def variable(self, key: str, latent: np.ndarray):
        """Adam's variable for u where a choice lays it out; None: as the scene's value."""
        made = [v for c in self.chain("variable", key) if (v := c.variable(key, latent))
                is not None]
        return made[0] if made else None

    def expand(self, key: str, latent):
        for c in self.chain("expand", key):
            latent = c.expand(key, latent)
        return latent

    def decode(self, key: str, latent):
        for c in self.chain("decode", key):
            latent = c.decode(key, latent)
        return latent

    def bounds(self, record: ParamRecord) -> tuple[float, float]:
        lo, hi = record.lo, record.hi
        for c in self.chain("bounds", record.key):
            lo, hi = c.bounds(record.key, lo, hi)
        return lo, hi

    def kept(self, record: ParamRecord) -> Kept:
        k = Kept(record.lo, record.hi)
        for c in self.chain("kept", record.key):
            k = c.kept(record.key, k)
        return k

    def rate(self, record: ParamRecord) -> float:
        rate = record.rate
        for c in self.chain("rate", record.key):
            rate = c.rate(record, rate)
        return rate

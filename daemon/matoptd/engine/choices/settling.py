"""Whether a variable still moves steadily, from its recent path: what eta's hold waits for in
the medium, and what makes eta's differences sparse once eta itself has settled.

Adam's step is about the rate when the gradient keeps its sign (m / sqrt(v) ~ 1), and a small
fraction of it when noise dominates, so over a window of steps the net move in units of the
steps the rates allowed,

    share = max_components |u_last - u_first| / sum of the rates of the steps taken,

is about 1 for a steady descent and a fraction for a variable jittering about its optimum
(momentum correlates the jitter over ~10 steps: 0.2-0.4 in trials). SETTLED splits the two.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

WINDOW = 10
SETTLED = 0.5


@dataclass
class Path:
    """A variable's last WINDOW + 1 values (in the space it is stepped in) and the rates of the
    WINDOW steps between them (0 for a step not taken)."""

    values: list[np.ndarray] = field(default_factory=list)
    rates: list[float] = field(default_factory=list)

    def add(self, value: np.ndarray, rate: float) -> None:
        """The value before this step and the rate the step will take it with."""
        self.values = (self.values + [np.asarray(value, np.float64)])[-WINDOW - 1:]
        self.rates = (self.rates + [rate])[-WINDOW - 1:]

    def settled(self, spread: bool = False) -> bool:
        """False until WINDOW steps are known. With ``spread`` the window's extent (max - min)
        stands for the move: a variable turning back at a swing's far end nets little over the
        window but spans much of it, and jitter spans little."""
        if len(self.values) <= WINDOW:
            return False
        allowed = sum(self.rates[-WINDOW - 1:-1])
        values = np.array(self.values)
        moved = float(np.max(np.ptp(values, axis=0) if spread
                             else np.abs(values[-1] - values[0])))
        return allowed <= 0 or moved < SETTLED * allowed

    def state(self, name: str) -> dict[str, np.ndarray]:
        """As arrays for a checkpoint (a job restored elsewhere decides as this one would)."""
        values = (np.array(self.values, np.float64).reshape(len(self.values), -1)
                  if self.values else np.zeros((0, 1)))
        return {f"{name}.values": values, f"{name}.rates": np.array(self.rates, np.float64)}

    @classmethod
    def restored(cls, state: dict[str, np.ndarray] | None, name: str) -> "Path":
        if not state or f"{name}.values" not in state:
            return cls()
        return cls(list(state[f"{name}.values"]), state[f"{name}.rates"].tolist())


def restored_paths(state: dict[str, np.ndarray] | None, keys) -> dict[str, Path]:
    """A Path per key, in the order of ``keys`` (their numbers in a checkpoint's state)."""
    return {k: Path.restored(state, f"path{n}") for n, k in enumerate(keys)}


def paths_state(paths: dict[str, Path]) -> dict[str, np.ndarray]:
    """The paths of restored_paths as a checkpoint's arrays."""
    out: dict[str, np.ndarray] = {}
    for n, path in enumerate(paths.values()):
        out.update(path.state(f"path{n}"))
    return out

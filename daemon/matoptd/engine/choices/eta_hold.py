"""A dielectric's eta held at its start while the medium behind it is still far off.

Far from the truth, the images ask eta for what the medium cannot give yet: on the thesis's
Table 4 scene (a rough dielectric around a homogeneous medium, started at albedo 0.01, sigma_t
0.99, alpha 0.98) eta ran from 1.55 to 1.70 in the first 20 iterations, its Fresnel reflection
standing in for the light a black medium did not scatter, and came back only slowly (final eta
5-9% off over three seeds). Eta is therefore held (no step: Adam leaves its value, moments
and step count alone, optimize._uncount) while a selected medium property or the microfacet
width beside eta still moves steadily (settling.py: over the last WINDOW
iterations it netted SETTLED or more of the steps its rate allowed). It is never held past
HOLD_SHARE of the job. Released, eta has its whole way to go in what is left of the job, so
its rate schedule's decay starts over from the release (``ParamRecord.schedule_begin``). On
Table 4 at max_depth 8, spp 8 (8 seeds, docs/benchmarks-history.md, 2026-11-29) the job's own
decay left eta's late steps at a tenth to a half of its rate, too small for its noisy
gradient to carry it: the median worst gated error was 9.6% that way and 5.6% restarted.

Only with a medium selected: without one, holding eta lets the others take up its error
instead. On the Table 3 kind (glass over a texture, eta from 1.64) eta held 15 iterations
ended at 1.505-1.553 over three seeds, against 1.494-1.498 stepped from the start, and the
texture further from the truth.
"""

from __future__ import annotations

import numpy as np

from ...engine_api import SMALL
from .. import parameters
from .base import HOLD, Choice
from .settling import SETTLED, WINDOW, paths_state, restored_paths

# Half, not less: held at most a fifth of the job on Table 4 (2026-12-02), eta was released
# while the medium still swung, climbed to its bound while the medium was dark and stayed
# there (max_depth 64, spp 32: 4.0% off at the end against 2.6% held to about iteration 45).
HOLD_SHARE = 0.5


class EtaHold(Choice):
    name = "eta_hold"
    yields_to = ("gauss_newton",)  # which steps eta by Gauss-Newton, while on

    def select(self, ctx, records):
        keys = [k for k, r in records.items() if r.scene is not None]
        etas = [k for k in keys if parameters.dielectric_eta(k)]
        media = [k for k in keys if parameters.medium_property(k)]
        widths = {w for eta in etas for w in parameters.microfacet_widths(eta, keys)}
        others = [k for k in keys if (k in widths or k in media)
                  and records[k].size <= SMALL] if media else []
        return etas + others if etas and others else []

    def setup(self, ctx, records, state) -> None:
        self.etas = [k for k in records if parameters.dielectric_eta(k)]
        self.others = [k for k in records if k not in self.etas]
        self.applies = bool(self.etas and self.others)
        saved = state.get("released") if state else None
        self.released = int(saved[0]) if saved is not None else -1  # the iteration; -1: held
        self.records = [records[k] for k in self.etas]
        self._restart()
        self.paths = restored_paths(state, self.others)
        self.last = max(1, round(HOLD_SHARE * ctx.settings.iterations))
        self.why = (f"{', '.join(self.etas)} held at its start until "
                    f"{', '.join(self.others)} settle (each nets less than {SETTLED:g} of its "
                    f"full steps over {WINDOW} iterations; at most until iteration {self.last}): "
                    "far off, the images push eta's reflection to stand in for the light the "
                    "medium does not scatter yet" if self.on else
                    f"{', '.join(self.etas)} stepped from the start")
        if self.released >= 0:
            self.why += f"; released at iteration {self.released}"

    def on_gradient(self, ctx) -> dict[str, object]:
        i = ctx.iteration
        if self.released >= 0:
            return {}
        for key, path in self.paths.items():
            path.add(ctx.latent(key), ctx.rate(key))
        if all(p.settled() for p in self.paths.values()) or i >= self.last:
            self.released = i
            self._restart()
            self.why += (f"; released at iteration {i} ("
                         + ("the others settled)" if i < self.last else "the hold's limit)"))
            return {}
        return dict.fromkeys(self.etas, HOLD)

    def _restart(self) -> None:
        # Released, eta has its whole way still to go: the schedule's decay runs from here
        for r in self.records:
            r.schedule_begin = max(self.released, 0)

    def state(self):
        return {"released": np.array([self.released], np.int64), **paths_state(self.paths)}

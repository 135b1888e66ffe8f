"""What to tell a user whose job did not converge, in words, from what the job saw."""

from __future__ import annotations

import numpy as np

ROUGHNESS_FLOOR = 0.03  # principled: alpha = max(0.001, roughness^2) hides roughness below this


def diagnose(settings: dict, values: dict[str, np.ndarray], losses: list[float],
             nonfinite_steps: int, skipped_steps: int) -> list[str]:
    notes = []
    for key, s in settings.items():
        v = values.get(key)
        if v is None:
            continue
        for bound, name in ((s.lo, "min"), (s.hi, "max")):
            at = int(np.sum(np.isclose(v, bound, rtol=0, atol=1e-6))) if np.isfinite(bound) else 0
            if at:
                notes.append(f"{key}: {at} component(s) ended at the {name} {bound:g}; the "
                             "truth may lie outside the range, or these images do not "
                             "constrain it")
        if key.endswith("roughness.value") and float(np.max(v)) < ROUGHNESS_FLOOR:
            notes.append(f"{key}: below ~{ROUGHNESS_FLOOR} the principled BSDF's alpha floor "
                         "(0.001) makes roughness invisible; compare alpha, not roughness")
    finite = [x for x in losses if np.isfinite(x)]
    if len(finite) >= 10:
        head, tail = np.mean(finite[:3]), np.mean(finite[-5:])
        if head > 0 and tail > 0.9 * head:
            notes.append(f"the loss fell by less than 10% ({head:.3g} -> {tail:.3g}): check "
                         "that the references show this scene from these sensors, or try more "
                         "iterations, more spp or a larger learning rate")
    if nonfinite_steps:
        notes.append(f"{nonfinite_steps} step(s) had NaN/Inf gradient components; they were "
                     "zeroed, and those components kept their values")
    if skipped_steps:
        notes.append(f"{skipped_steps} step(s) were skipped: the loss was NaN/Inf")
    return notes

"""The diagnosis of where the images do not decide, as pure logic on synthetic histories:
no renderer, no daemon."""

from __future__ import annotations

import numpy as np
import pytest

from matoptd.engine.diagnosis import (Kept, diagnose, drifts_from_truth, moving, steered,
                                      trade_offs, undecided, unmoved)
from matoptd.engine.parameters import ROUGHNESS_FLOOR

N = 100


def _noise(seed: int, scale: float) -> np.ndarray:
    return np.random.default_rng(seed).normal(0, scale, N)


def _falling_then_level(seed: int = 0) -> list[float]:
    """A loss that falls for 30 iterations, then stays level with noise."""
    i = np.arange(N)
    return list(0.001 + 0.05 * np.exp(-i / 8) + _noise(seed, 5e-5))


def test_texture_absorbing_spec_trans_is_reported_against_the_truth():
    # The thesis's Table 3 kind: spec_trans (truth 1.0) falls from 0.1 to 0 while the texture
    # takes over the look; the render matches, the error against the truth grows to 1.
    losses = _falling_then_level()
    spec = np.maximum(0.1 - 0.02 * np.arange(N), 0.0)
    errors = {"obj.spec_trans": list(np.abs(spec - 1.0)),
              "obj.eta": list(0.1 * np.exp(-np.arange(N) / 10) + 0.002)}
    found = drifts_from_truth(losses, errors)
    assert [f[0] for f in found] == ["obj.spec_trans"]
    key, first, lowest, last = found[0]
    assert first == 0.9 and lowest == 0.9 and last == 1.0
    note = undecided(losses, {}, errors).notes[0]
    assert "obj.spec_trans" in note and "do not decide" in note and "more views" in note


def test_a_scalar_that_jumps_to_its_bound_at_once_is_reported():
    # spec_trans 0.1 -> 0 in one step (truth 1.0): the error goes 0.9 -> 1.0 and stays there.
    losses = _falling_then_level()
    errors = {"obj.spec_trans": [0.9] + [1.0] * (N - 1)}
    assert [f[0] for f in drifts_from_truth(losses, errors)] == ["obj.spec_trans"]


def test_a_noisy_converged_error_is_not_reported():
    losses = _falling_then_level()
    errors = {"obj.eta": list(0.004 + np.abs(_noise(11, 0.004)))}
    assert drifts_from_truth(losses, errors) == []


def test_converging_parameters_are_not_reported():
    losses = _falling_then_level()
    errors = {"obj.base_color": list(0.9 * np.exp(-np.arange(N) / 10) + 0.01
                                     + np.abs(_noise(1, 0.003)))}
    paths = {"obj.base_color": (0.41 - 0.3 * np.exp(-np.arange(N) / 10)
                                + _noise(2, 0.002))[:, None],
             "obj.eta": (1.49 + 0.05 * np.exp(-np.arange(N) / 10) + _noise(3, 0.001))[:, None]}
    assert drifts_from_truth(losses, errors) == []
    assert trade_offs(losses, paths) == []
    assert unmoved(paths, losses) == []


def test_error_growing_while_the_loss_falls_further_is_reported_but_not_while_it_rises():
    i = np.arange(N)
    errors = {"obj.eta": list(np.where(i < 30, 0.05 - 0.0015 * i, 0.005 + 0.002 * (i - 30)))}
    falling = list(0.01 * np.exp(-i / 30))
    assert [f[0] for f in drifts_from_truth(falling, errors)] == ["obj.eta"]
    # The loss rose with the error: the images did steer it, the optimizer went astray.
    rising = list(0.001 + 0.0001 * i)
    assert drifts_from_truth(rising, errors) == []


def test_two_parameters_drifting_against_each_other_on_a_level_loss_trade_off():
    # eta against base_color where transmission never shows: both wander along a valley.
    losses = list(0.002 + _noise(4, 5e-5))
    walk = np.r_[np.zeros(50), 0.05 * np.sin(np.linspace(0, 3 * np.pi, 50))]
    paths = {"obj.eta": (1.5 + walk + _noise(5, 0.0005))[:, None],
             "obj.base_color": np.stack([0.4 - 0.5 * walk + _noise(6 + c, 0.0005)
                                         for c in range(3)], axis=1),
             "obj.roughness": (0.2 + _noise(9, 0.0005))[:, None]}
    found = trade_offs(losses, paths)
    assert len(found) == 1
    a, b, r, _ = found[0]
    assert {a, b} == {"obj.eta", "obj.base_color"} and r < -0.8
    note = undecided(losses, paths, {}).notes[0]
    assert "trade off" in note and "obj.eta" in note and "another sensor" in note


def test_no_trade_off_while_two_parameters_still_head_one_way_on_a_noisy_loss():
    # Converging in step, slower than the noise lets the loss show: not a valley.
    i = np.arange(N)
    losses = list(0.002 + _noise(10, 5e-5))
    paths = {"albedo": (0.3 + 0.001 * i)[:, None], "sigma_t": (0.6 - 0.002 * i)[:, None]}
    assert trade_offs(losses, paths) == []


def test_no_trade_off_while_the_loss_is_still_falling():
    # Two parameters converging together move in step too, but the loss falls meanwhile.
    i = np.arange(N)
    losses = list(0.05 * np.exp(-i / 40))
    paths = {"a": (0.5 + 0.3 * (1 - np.exp(-i / 40)))[:, None],
             "b": (1.0 + 0.3 * (1 - np.exp(-i / 40)))[:, None]}
    assert trade_offs(losses, paths) == []


def test_a_parameter_without_gradient_is_reported_as_unmoved():
    losses = _falling_then_level()
    paths = {"obj.eta": np.full((N, 1), 1.54),
             "obj.base_color": (0.41 - 0.3 * np.exp(-np.arange(N) / 10))[:, None]}
    assert unmoved(paths, losses) == ["obj.eta"]
    note = undecided(losses, paths, {}).notes[0]
    assert "obj.eta hardly moved" in note and "max_depth" in note


def test_diagnose_passes_the_truth_errors_through():
    losses = _falling_then_level()
    spec = np.maximum(0.1 - 0.02 * np.arange(N), 0.0)
    notes = diagnose({"obj.spec_trans": Kept(0.0, 1.0)}, {"obj.spec_trans": np.array([0.0])}, losses, 0, 0,
                     {"obj.spec_trans": spec[:, None]},
                     {"obj.spec_trans": list(np.abs(spec - 1.0))}).notes
    assert any("do not decide" in n for n in notes)
    assert any("ended on its lower bound 0" in n for n in notes)


_ROUGHNESS = Kept(0.01, 1.0, ROUGHNESS_FLOOR, log=True)


def _drifting_roughness() -> tuple[list[float], dict[str, np.ndarray]]:
    """The Table 2 kind at 48 px: the loss is level (noise 1e-4 about 1e-3) while roughness
    drifts from 0.060 to 0.066 over the last fifth."""
    losses = list(0.001 + _noise(4, 1e-4))
    path = np.concatenate([np.geomspace(0.5, 0.06, 80), np.linspace(0.06, 0.066, 20)])
    return losses, {"blob.roughness": path[:, None]}


def _notes(gradients: list[np.ndarray] | None) -> list[str]:
    losses, paths = _drifting_roughness()
    return diagnose({"blob.roughness": _ROUGHNESS}, {"blob.roughness": np.array([0.066])},
                    losses, 0, 0, paths,
                    gradients=None if gradients is None else {"blob.roughness": gradients}).notes


def test_a_drift_on_gradients_without_a_consistent_sign_is_noise_not_convergence():
    losses, paths = _drifting_roughness()
    assert list(moving({"blob.roughness": _ROUGHNESS}, paths)) == ["blob.roughness"]
    # Zero-mean gradients of spread 1: their mean over 20 steps is within two standard errors.
    noise = [np.array([g]) for g in _noise(6, 1.0)[:99]]
    assert steered(noise[-20:])[0] is False
    drift = [n for n in _notes(noise) if n.startswith("blob.roughness drifted")]
    assert len(drift) == 1
    assert "(0.06142 -> 0.06458 over its last 20 iterations) on noise" in drift[0]
    assert not any("still moving" in n for n in _notes(noise))


def test_a_drift_on_a_consistent_gradient_is_still_moving():
    # The same drift on gradients of mean -1 (pushing it up) and spread 1: the images steer it.
    steady = [np.array([g - 1.0]) for g in _noise(6, 1.0)[:99]]
    assert steered(steady[-20:])[0] is True
    notes = _notes(steady)
    assert any(n.startswith("blob.roughness was still moving") for n in notes), notes
    assert not any("on noise" in n for n in notes)
    # One component of an RGB value with a consistent gradient is enough.
    rgb = [np.array([g, -1.0 + g, g]) for g in _noise(7, 1.0)[:20]]
    assert steered(rgb)[0] is True
    # Too few steps (a job resumed on this worker near its end) leave it as it was.
    assert steered([np.array([0.1])] * 4) is None
    # Held steps (a choice zeroed the gradient, recorded as NaN) are not the images': the
    # consistent gradient between them still shows, and too few of them say nothing.
    held = [np.array([np.nan])] * 3
    assert steered([x for g in steady[-10:] for x in (g, *held)])[0] is True
    assert steered([x for g in steady[-4:] for x in (g, *held)]) is None
    assert any("still moving" in n for n in _notes(None))


def _at_floor(gradients: list[np.ndarray] | None) -> list[str]:
    """A principled roughness shown at the floor over its last 30 iterations."""
    path = np.concatenate([np.geomspace(0.5, ROUGHNESS_FLOOR, 70), np.full(30, ROUGHNESS_FLOOR)])
    notes = diagnose({"blob.roughness": _ROUGHNESS},
                     {"blob.roughness": np.array([ROUGHNESS_FLOOR], np.float32)},
                     list(0.001 + _noise(4, 1e-4)), 0, 0, {"blob.roughness": path[:, None]},
                     gradients=None if gradients is None else {"blob.roughness": gradients}).notes
    return [n for n in notes if n.startswith("blob.roughness")]


def test_a_roughness_at_the_floor_is_told_by_the_sign_of_its_gradient_there():
    # Positive gradients push it lower: the images say the truth is at or below the floor.
    pressed = _at_floor([np.array([g + 1.0]) for g in _noise(8, 1.0)[:40]])
    assert len(pressed) == 1 and "kept pressing it there" in pressed[0], pressed
    # No consistent sign: the images do not tell the floor from a slightly rougher surface.
    level = _at_floor([np.array([g]) for g in _noise(6, 1.0)[:40]])
    assert len(level) == 1 and "no consistent sign" in level[0] and "would decide" in level[0]
    # Negative gradients pull it up (below the floor, on its way out): not converged.
    pulled = _at_floor([np.array([g - 1.0]) for g in _noise(8, 1.0)[:40]])
    assert len(pulled) == 1 and "pulling it up" in pulled[0], pulled
    # Without gradient records (a job resumed on another worker) it says what the floor means.
    assert "anywhere below" in _at_floor(None)[0]
    assert all("alpha floor" in n for n in pressed + level + pulled)

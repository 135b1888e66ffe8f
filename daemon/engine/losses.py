"""Image losses. Each takes the renders of one sensor and its reference and returns a scalar
Dr.Jit value with gradients. ``renders`` says how many independent renders a loss needs."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import drjit as dr
import mitsuba as mi

from matopt.v1 import matopt_pb2 as pb


@dataclass(frozen=True)
class Loss:
    name: str
    renders: int
    fn: Callable[[list[mi.TensorXf], mi.TensorXf], mi.TensorXf]  # shape ()


def _mse(images: list[mi.TensorXf], ref: mi.TensorXf) -> mi.TensorXf:
    # L2 = mean over pixels and channels of (I - R)^2.
    return dr.mean(dr.square(images[0] - ref), axis=None)


def _dual_buffer(images: list[mi.TensorXf], ref: mi.TensorXf) -> mi.TensorXf:
    # Deng et al. 2022: with two renders A, B of independent noise,
    #   E[(A - R)(B - R)] = (E[A] - R)^2,
    # so the noise that biases plain MSE at low spp cancels. A single estimate can be < 0.
    return dr.mean((images[0] - ref) * (images[1] - ref), axis=None)


LOSSES = {
    pb.MSE: Loss("mse", 1, _mse),
    pb.DUAL_BUFFER: Loss("dual_buffer", 2, _dual_buffer),
}

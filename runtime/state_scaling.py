"""The conversion between the physical state a user gives and reads and the scaled state the
kernels of a scaled build carry (codegen/scaling.py): x = offset + scale x~, P = S P~ S."""
from __future__ import annotations

import numpy as np


class StateScaling:
    """x = offset + scale x~, P = S P~ S (S = diag(scale)): the conversion between the physical
    state a user gives and reads and the scaled state the kernels of a scaled build carry
    (codegen/scaling.py). Done in double; scales are powers of two, so it is exact."""

    def __init__(self, description: dict):
        info = description["state_scaling"]
        self.scale, self.offset = np.array(info["scale"]), np.array(info["offset"])
        self.outer = np.outer(self.scale, self.scale)
        #: Q is n x n in state units (additive noise) unless the model declares noises w.
        self.scales_Q = not description.get("noises")

    @staticmethod
    def of(description: dict) -> "StateScaling | None":
        info = description.get("state_scaling")
        return StateScaling(description) if info and info["kernels_use_scaled_state"] else None

    def x_to_kernel(self, x: np.ndarray) -> np.ndarray:
        return (x - self.offset) / self.scale

    def x_from_kernel(self, x: np.ndarray) -> np.ndarray:
        return self.offset + self.scale * np.asarray(x, dtype=float)

    def P_to_kernel(self, P: np.ndarray) -> np.ndarray:
        return P / self.outer

    def P_from_kernel(self, P: np.ndarray) -> np.ndarray:
        return np.asarray(P, dtype=float) * self.outer

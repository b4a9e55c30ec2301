"""What every NumPy reference shares: angle wrapping as the generated code does it, a symmetrised
covariance, and the initial state of a Kalman-type reference."""
from __future__ import annotations

import numpy as np


def wrap_angle(a):
    """Wrap to (-pi, pi], the same formula as the generated code (codegen.linalg.wrap_angle)."""
    return a - 2 * np.pi * np.ceil((a - np.pi) / (2 * np.pi))



def _init_filter_state(ref, model, x0, P0, Q, p, R) -> None:
    """The state every Kalman-type reference starts from: x, P, Q, parameters, inputs, per
    measurement its wrap flags and R (default diag(sigma^2)), no innovation yet."""
    ref.x, ref.P, ref.Q = np.array(x0, float), np.array(P0, float), np.array(Q, float)
    ref.p = np.array(model.param_defaults if p is None else p, float)
    ref.u = np.zeros(len(model.inputs))
    ref.wrap = {name: np.array(m.wrap) for name, m in model.measurements.items()}
    ref.R = {name: np.diag(m.sigma**2) for name, m in model.measurements.items()}
    ref.R.update(R or {})
    ref.y = ref.S = None


def _sym(A):
    return 0.5 * (A + A.T)

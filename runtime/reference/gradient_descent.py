"""NumPy reference of the gradient-descent orientation filter (paper 001, eqs (7)-(9), (13),
(26)-(31)), around the model's CasADi gradients (``codegen/families/gradient_descent.py``)."""
from __future__ import annotations

import casadi as ca
import numpy as np

from symkf.codegen.families.gradient_descent import ZERO_NORM, marg_functions
from symkf.models.marg import ALPHA_DEFAULT, BETA_MADGWICK


def _call(function: ca.Function, *args) -> np.ndarray:
    return np.asarray(function(*args)).ravel()


def _unit_or_zero(v: np.ndarray) -> tuple[np.ndarray, bool]:
    largest = np.max(np.abs(v))
    scaled = v / largest if largest > 0 else v
    norm = np.linalg.norm(scaled)
    return (scaled / norm, True) if largest * norm > ZERO_NORM else (np.zeros(3), False)


def reference_direction(q: np.ndarray, acc: np.ndarray, mag: np.ndarray | None) -> np.ndarray:
    """Eq (27) normalised, in NumPy around the model's CasADi gradients; zero when not correctable."""
    fns = marg_functions()
    a, acc_ok = _unit_or_zero(acc)
    m, mag_ok = _unit_or_zero(mag) if mag is not None else (np.zeros(3), False)
    if mag_ok:
        b = _call(fns["earth_field_reference"], q, m)
    if acc_ok and mag_ok:
        grad = _call(fns["gradient_stacked"], q, a, b, m)
    elif acc_ok:
        grad = _call(fns["gradient_gravity"], q, a)
    elif mag_ok:
        grad = _call(fns["gradient_earth_field"], q, b, m)
    else:
        return np.zeros(4)
    norm = np.linalg.norm(grad)
    return grad / norm if norm > ZERO_NORM else np.zeros(4)


def reference_step(form: str, q: np.ndarray, dt: float, gyro, acc, mag, beta: float, alpha: float) -> np.ndarray:
    """One step of (26)-(30) or (31) in NumPy (the model's equations evaluated by CasADi)."""
    q_dot = _call(marg_functions()["quaternion_rate"], q, gyro)        # (7)-(8)
    direction = reference_direction(q, np.asarray(acc, float), None if mag is None else np.asarray(mag, float))
    if form == "simple":
        q_est = q + (q_dot - beta * direction) * dt                    # (31)
    else:
        rate_nabla = alpha * np.linalg.norm(q_dot)                     # μ_t/Δt (28)
        corrected = bool(direction.any()) and rate_nabla + beta > 0
        gamma = beta / (rate_nabla + beta) if corrected else 0.0       # (30)
        q_est = gamma * (q - rate_nabla * dt * direction) + (1 - gamma) * (q + q_dot * dt)   # (26), (9), (29)
    return q_est / np.linalg.norm(q_est)


def reference_run(form: str, mode: str, q0, dt, gyro, acc, mag=None, beta: float = BETA_MADGWICK,
                  alpha: float = ALPHA_DEFAULT) -> np.ndarray:
    """The NumPy reference over N samples: (N, 4) estimates, the same contract as :meth:`MargFilter.run`."""
    q = np.asarray(q0, dtype=float).copy()
    out = np.zeros((len(dt), 4))
    for k in range(len(dt)):
        q = reference_step(form, q, dt[k], gyro[k], acc[k], mag[k] if mode == "marg" else None, beta, alpha)
        out[k] = q
    return out


def reference_initial(acc, mag) -> np.ndarray:
    """Initial orientation (TRIAD, 9-axis) via the model's CasADi function."""
    return _call(marg_functions()["initial_orientation"], acc, mag)


class ReferenceMarg:
    """NumPy reference of :class:`~symkf.scenarios.marg.filter.MargFilter`: state ``x`` = q, ``step`` per sample."""

    def __init__(self, form: str, mode: str, q0, beta: float = BETA_MADGWICK, alpha: float = ALPHA_DEFAULT):
        self.form, self.mode, self.beta, self.alpha = form, mode, beta, alpha
        self.x = np.asarray(q0, dtype=float).copy()

    def step(self, dt: float, gyro, acc, mag=None) -> np.ndarray:
        self.x = reference_step(self.form, self.x, dt, gyro, acc, mag if self.mode == "marg" else None,
                                self.beta, self.alpha)
        return self.x

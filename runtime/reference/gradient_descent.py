"""NumPy reference of the gradient-descent orientation filter (paper 001, eqs (7)-(9), (13),
(26)-(31)), around the model's equations as ``codegen/families/gradient_descent.py`` takes them
(:func:`~symkf.codegen.families.gradient_descent.model_functions`), with the compiled filters'
canonical arguments: ``step(t, dt, z, measurement, u=gyro, mask=...)``."""
from __future__ import annotations

import casadi as ca
import numpy as np

from symkf.codegen.families.gradient_descent import (EARTH_FIELD_REFERENCE, FORMS, INITIAL_ORIENTATION, ZERO_NORM,
                                                     model_functions)
from symkf.models import get_model


def _call(function: ca.Function, *args) -> np.ndarray:
    return np.asarray(function(*args)).ravel()


def _unit_or_zero(v: np.ndarray) -> tuple[np.ndarray, bool]:
    largest = np.max(np.abs(v))
    scaled = v / largest if largest > 0 else v
    norm = np.linalg.norm(scaled)
    return (scaled / norm, True) if largest * norm > ZERO_NORM else (np.zeros(3), False)


def _sample(z: np.ndarray, mask: np.ndarray, rows: slice) -> tuple[np.ndarray, bool]:
    """A vector sample normalised, and whether it is present (mask) and not zero-norm."""
    if not np.all(mask[rows] > 0.5):
        return np.zeros(3), False
    return _unit_or_zero(z[rows])


class ReferenceGradientDescent:
    """Filter ``gd_simple`` (eq (31)) or ``gd_full`` (eqs (26)-(30)) in NumPy: state ``x`` = q
    (scalar-last), parameters ``p`` = [beta, alpha], gyro ``u``; measurements "imu" and "marg"."""

    def __init__(self, model_name, family: str, x0, p=None):
        form = family.removeprefix("gd_")
        if form not in FORMS:
            raise ValueError(f"family: expected one of {['gd_' + f for f in FORMS]}, got {family!r}")
        model = get_model(model_name)
        self.fns = model_functions(model)
        self.form = form
        self.x = np.asarray(x0, dtype=float).copy()
        self.p = np.asarray(model.param_defaults if p is None else p, dtype=float)
        self.u = np.zeros(len(model.inputs))
        self.t = 0.0

    def direction(self, name: str, z: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """Eq (27) normalised; zero when no sample corrects."""
        x, u, p, fns = self.x, self.u, self.p, self.fns
        a, acc_ok = _sample(z, mask, slice(0, 3))
        if name == "imu":
            grad = _call(fns["gradient_imu"], x, u, p, np.zeros(0), a) if acc_ok else None
        else:
            m, mag_ok = _sample(z, mask, slice(3, 6))
            b = _call(fns[EARTH_FIELD_REFERENCE], x, m) if mag_ok else None
            if acc_ok and mag_ok:
                grad = _call(fns["gradient_marg"], x, u, p, b, np.r_[a, m])
            elif acc_ok:
                grad = _call(fns["gradient_marg_gravity"], x, u, p, np.zeros(2), a)
            elif mag_ok:
                grad = _call(fns["gradient_marg_earth_field"], x, u, p, b, m)
            else:
                grad = None
        if grad is None:
            return np.zeros(4)
        norm = np.linalg.norm(grad)
        return grad / norm if norm > ZERO_NORM else np.zeros(4)

    def step(self, t: float, dt: float, z, measurement: str, u=None, mask=None) -> np.ndarray:
        """One sample: gyro ``u`` (rad/s), samples z (any units; mask 0 or a zero vector skips one)."""
        z = np.asarray(z, dtype=float)
        mask = np.ones(z.size) if mask is None else np.asarray(mask, dtype=float)
        if u is not None:
            self.u = np.asarray(u, dtype=float)
        q, beta, alpha = self.x, self.p[0], self.p[1]
        q_dot = _call(self.fns["quaternion_rate"], q, self.u, self.p)      # (7)-(8)
        direction = self.direction(measurement, z, mask)
        if self.form == "simple":
            q_est = q + (q_dot - beta * direction) * dt                    # (31)
        else:
            rate_nabla = alpha * np.linalg.norm(q_dot)                     # μ_t/Δt (28)
            corrected = bool(direction.any()) and rate_nabla + beta > 0
            gamma = beta / (rate_nabla + beta) if corrected else 0.0       # (30)
            q_est = gamma * (q - rate_nabla * dt * direction) + (1 - gamma) * (q + q_dot * dt)   # (26), (9), (29)
        self.x = q_est / np.linalg.norm(q_est)
        self.t = t + dt
        return self.x

    def run(self, times, z, measurement: str, u=None, mask=None) -> np.ndarray:
        """Steps over a record (dt from the times, the first 0), as :meth:`Filter.run`: (N, 4) estimates."""
        times = np.asarray(times, dtype=float)
        dt = np.diff(times, prepend=times[:1])
        out = np.zeros((times.size, self.x.size))
        for k in range(times.size):
            self.step(times[k] - dt[k], dt[k], z[k], measurement, None if u is None else u[k],
                      None if mask is None else mask[k])
            out[k] = self.x
        return out

    def initial(self, z) -> np.ndarray:
        """Initial orientation (TRIAD) from a 9-axis sample z = [acc, mag], the model's function."""
        z = np.asarray(z, dtype=float)
        return _call(self.fns[INITIAL_ORIENTATION], z[:3], z[3:6])

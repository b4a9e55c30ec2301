"""Model -> CasADi Functions: continuous dynamics, RK4 discretisation, derived Jacobians.

The discrete step is classic fourth-order Runge-Kutta with ``substeps`` equal sub-steps over
[t, t + dt], inputs held constant (zero-order hold). Jacobians F = d f_d / d x and
H = d h / d x are derived by CasADi; nothing here is typed by hand.
"""
from __future__ import annotations

import casadi as ca

from symkf.models.base import Model

FUNCTION_OPTIONS = {"cse": True, "allow_duplicate_io_names": True}


def continuous_dynamics(model: Model) -> ca.Function:
    """f(t, x, u, p, w) -> dx/dt."""
    return ca.Function("f", [model.t, model.x, model.u, model.p, model.w], [model.f],
                       ["t", "x", "u", "p", "w"], ["xdot"], FUNCTION_OPTIONS)


def rk4(f: ca.Function, t, dt, x, u, p, w, substeps: int):
    """Symbolic RK4 of dx/dt = f(t, x, u, p, w) from t to t + dt in ``substeps`` steps."""
    if substeps < 1:
        raise ValueError(f"rk4 substeps must be >= 1, got {substeps}")
    h = dt / substeps
    for i in range(substeps):
        ti = t + i * h
        k1 = f(ti, x, u, p, w)
        k2 = f(ti + h / 2, x + h / 2 * k1, u, p, w)
        k3 = f(ti + h / 2, x + h / 2 * k2, u, p, w)
        k4 = f(ti + h, x + h * k3, u, p, w)
        x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return x


def discrete_dynamics(model: Model, substeps: int) -> ca.Function:
    """f_d(t, dt, x, u, p, w) -> x(t + dt) by RK4 with ``substeps`` sub-steps."""
    f = continuous_dynamics(model)
    dt = ca.SX.sym("dt")
    x_next = rk4(f, model.t, dt, model.x, model.u, model.p, model.w, substeps)
    return ca.Function("fd", [model.t, dt, model.x, model.u, model.p, model.w], [x_next],
                       ["t", "dt", "x", "u", "p", "w"], ["x_next"], FUNCTION_OPTIONS)


def measurement_function(model: Model, name: str) -> ca.Function:
    """h(t, x, u, p, q) -> z for the named measurement."""
    meas = model.measurements[name]
    return ca.Function(f"h_{name}", [model.t, model.x, model.u, model.p, meas.q], [meas.h],
                       ["t", "x", "u", "p", "q"], ["z"], FUNCTION_OPTIONS)

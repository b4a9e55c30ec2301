"""Model -> CasADi Functions: continuous dynamics, discretisation, derived Jacobians.

The discrete step integrates [t, t + dt] with ``substeps`` equal sub-steps of classic
fourth-order Runge-Kutta (or explicit Euler, a per-filter choice), inputs held constant
(zero-order hold). Jacobians F = d f_d / d x and H = d h / d x are derived by CasADi; nothing
here is typed by hand.

Events. A model that declares known switching times (``Model.events``: staging, ignition,
burnout) gets a step that never straddles one: [t, t + dt] is cut at the first event t_e in
(t, t + dt), and [t, t_e] and [t_e, t + dt] are integrated separately (each with ``substeps``
sub-steps; a step holding no event has an empty second part, which leaves x exactly as it is).
On [t, t_e] the dynamics' time argument is held at most ``EVENT_INSET`` before t_e, so every RK
stage sees the before-event dynamics; from t_e on the model's right-continuous schedule gives
the after-event ones. The cut is branch-free (fmin/fmax/if_else of the event constants), so the
generated C does the same. At most one event per step is split: steps must be shorter than the
shortest gap between events (22.9 s for the launcher).
"""
from __future__ import annotations

import casadi as ca

from symkf.models.base import Model

FUNCTION_OPTIONS = {"cse": True, "allow_duplicate_io_names": True}
#: s: how far before an event the time argument is held on the segment that ends there (the
#: truth simulator uses the same inset, scenarios/launcher/truth.py).
EVENT_INSET = 1e-6
INTEGRATORS = ("rk4", "euler")


def continuous_dynamics(model: Model) -> ca.Function:
    """f(t, x, u, p, w) -> dx/dt."""
    return ca.Function("f", [model.t, model.x, model.u, model.p, model.w], [model.f],
                       ["t", "x", "u", "p", "w"], ["xdot"], FUNCTION_OPTIONS)


def rk4(f, t, dt, x, u, p, w, substeps: int, latest=None):
    """Symbolic RK4 of dx/dt = f(t, x, u, p, w) from t to t + dt in ``substeps`` steps; the time
    argument of f is capped at ``latest`` when given (the segment before an event)."""
    return integrate(f, t, dt, x, u, p, w, substeps, "rk4", latest)


def integrate(f, t, dt, x, u, p, w, substeps: int, method: str = "rk4", latest=None):
    """``substeps`` steps of RK4 or explicit Euler from t to t + dt (no event handling)."""
    if substeps < 1:
        raise ValueError(f"integrator substeps must be >= 1, got {substeps}")
    if method not in INTEGRATORS:
        raise ValueError(f"integrator: expected one of {INTEGRATORS}, got '{method}'")

    def rate(ti, xi):
        return f(ti if latest is None else ca.fmin(ti, latest), xi, u, p, w)

    h = dt / substeps
    for i in range(substeps):
        ti = t + i * h
        k1 = rate(ti, x)
        if method == "euler":
            x = x + h * k1
            continue
        k2 = rate(ti + h / 2, x + h / 2 * k1)
        k3 = rate(ti + h / 2, x + h / 2 * k2)
        k4 = rate(ti + h, x + h * k3)
        x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return x


def first_event_after(t, events, otherwise):
    """The first of the (increasing) event times strictly after t, else ``otherwise``."""
    result = otherwise
    for event in sorted(events, reverse=True):
        result = ca.if_else(t < event, event, result)
    return result


def event_split_step(f, t, dt, x, u, p, w, events, substeps: int, method: str = "rk4"):
    """x(t + dt) integrated over [t, t_e] and [t_e, t + dt], t_e the first event in (t, t + dt)."""
    end = t + dt
    event = first_event_after(t, events, end + 1.0)
    cut = ca.fmin(event, end)
    x_cut = integrate(f, t, cut - t, x, u, p, w, substeps, method, latest=event - EVENT_INSET)
    return integrate(f, cut, end - cut, x_cut, u, p, w, substeps, method)


def discrete_step(model: Model, f, t, dt, x, u, p, w, substeps: int, method: str = "rk4",
                  split_events: bool = True):
    """The discrete step of the model's dynamics, split at its events when asked (and it has any)."""
    if split_events and model.events:
        return event_split_step(f, t, dt, x, u, p, w, model.events, substeps, method)
    return integrate(f, t, dt, x, u, p, w, substeps, method)


def discrete_dynamics(model: Model, substeps: int, method: str = "rk4", split_events: bool = True) -> ca.Function:
    """f_d(t, dt, x, u, p, w) -> x(t + dt) by RK4 (or Euler) with ``substeps`` sub-steps, split at
    the model's events unless ``split_events`` is False."""
    f = continuous_dynamics(model)
    dt = ca.SX.sym("dt")
    x_next = discrete_step(model, f, model.t, dt, model.x, model.u, model.p, model.w, substeps, method, split_events)
    return ca.Function("fd", [model.t, dt, model.x, model.u, model.p, model.w], [x_next],
                       ["t", "dt", "x", "u", "p", "w"], ["x_next"], FUNCTION_OPTIONS)


def measurement_function(model: Model, name: str) -> ca.Function:
    """h(t, x, u, p, q) -> z for the named measurement."""
    meas = model.measurements[name]
    return ca.Function(f"h_{name}", [model.t, model.x, model.u, model.p, meas.q], [meas.h],
                       ["t", "x", "u", "p", "q"], ["z"], FUNCTION_OPTIONS)

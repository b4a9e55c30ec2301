"""Model -> CasADi Functions: continuous dynamics, discretisation, derived Jacobians.

The discrete step integrates [t, t + dt] with ``substeps`` equal sub-steps of classic
fourth-order Runge-Kutta (or explicit Euler, a per-filter choice), inputs held constant
(zero-order hold). Jacobians F = d f_d / d x and H = d h / d x are derived by CasADi; nothing
here is typed by hand.

Events. A model that declares known switching times (``Model.events``: staging, ignition,
burnout) gets a step that never straddles one: [t, t + dt] is cut at the first event t_e in
(t, t + dt], and [t, t_e] and [t_e, t + dt] are integrated separately (each with ``substeps``
sub-steps). On [t, t_e] the dynamics' time argument is held at most ``EVENT_INSET`` before t_e,
so every RK stage sees the before-event dynamics; from t_e on the model's right-continuous
schedule gives the after-event ones. At most one event per step is split: steps must be shorter
than the shortest gap between events (22.9 s for the launcher).

The step *branches* (:class:`EventBranches`): almost no step holds an event (4 of the 8,686 steps
of a 20 Hz launcher flight), so a plain branch integrates [t, t + dt] once and a split branch
integrates the two parts; a CasADi ``Function.conditional`` picks one from the event flag, and the
generated C evaluates only the chosen branch (an ``if`` around two function calls). Each branch
is an SX function, so its Jacobian and everything built on it (``EventBranches.function``) is
derived per branch. The plain branch is the split branch's arithmetic with an empty second part:
it integrates over h = (t + dt) - t, which is what the split branch does when the first event is
past t + dt, so both give the same numbers (the empty part only adds zeros).
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


def event_in_step(t, dt, events):
    """1 if one of the model's events lies in (t, t + dt] (the step is split there), else 0."""
    end = t + dt
    return first_event_after(t, events, end + 1.0) <= end


class EventBranches:
    """The discrete step of a model as SX branches and the flag that picks one of them.

    ``branches`` is ``(plain,)`` for a model without events (or with ``split_events`` off), else
    ``(plain, split)``; each is an SX Function f_d(t, dt, x, u, p, w) -> x(t + dt). Call
    :meth:`function` to build any function of the step (f_d, its Jacobian, sigma points
    propagated) once per branch and select the branch at run time.
    """

    def __init__(self, model: Model, substeps: int, method: str = "rk4", split_events: bool = True):
        self.model, self.events = model, tuple(model.events) if split_events else ()
        f = continuous_dynamics(model)
        dt = ca.SX.sym("dt")
        args = [model.t, dt, model.x, model.u, model.p, model.w]
        names = ["t", "dt", "x", "u", "p", "w"]
        t, x, u, p, w = model.t, model.x, model.u, model.p, model.w
        if not self.events:
            plain = integrate(f, t, dt, x, u, p, w, substeps, method)
            self.branches = (ca.Function("fd", args, [plain], names, ["x_next"], FUNCTION_OPTIONS),)
            return
        # (t + dt) - t, not dt: the split branch's first part when no event is inside (same numbers)
        plain = integrate(f, t, (t + dt) - t, x, u, p, w, substeps, method)
        split = event_split_step(f, t, dt, x, u, p, w, self.events, substeps, method)
        self.branches = (ca.Function("fd_plain", args, [plain], names, ["x_next"], FUNCTION_OPTIONS),
                         ca.Function("fd_split", args, [split], names, ["x_next"], FUNCTION_OPTIONS))

    def function(self, name: str, inputs: list[ca.SX], input_names: list[str], outputs, output_names: list[str],
                 options: dict) -> ca.Function:
        """``name``(inputs) -> ``outputs(fd)`` with fd each branch in turn: one SX Function without
        events, else an MX Function whose ``Function.conditional`` evaluates the plain branch, or
        the split one when an event lies in (t, t + dt] (``inputs`` start with t and dt)."""
        made = [ca.Function(f"{name}_{tag}", inputs, outputs(fd), input_names, output_names, options)
                for tag, fd in zip(("plain", "split"), self.branches)]
        if len(made) == 1:
            return ca.Function(name, inputs, outputs(self.branches[0]), input_names, output_names, options)
        switch = ca.Function.conditional(f"{name}_branch", [made[0]], made[1])
        sym = [ca.MX.sym(n, *v.shape) for n, v in zip(input_names, inputs)]
        flag = event_in_step(sym[0], sym[1], self.events)
        return ca.Function(name, sym, switch.call([flag, *sym]), input_names, output_names, options)


def discrete_step(model: Model, f, t, dt, x, u, p, w, substeps: int, method: str = "rk4",
                  split_events: bool = True):
    """x(t + dt) as one SX expression, split at the model's events when asked (and it has any):
    branch-free, both parts always integrated (for kernels that inline f_d; :class:`EventBranches`
    evaluates only the part a step needs)."""
    if split_events and model.events:
        return event_split_step(f, t, dt, x, u, p, w, model.events, substeps, method)
    return integrate(f, t, dt, x, u, p, w, substeps, method)


def discrete_dynamics(model: Model, substeps: int, method: str = "rk4", split_events: bool = True) -> ca.Function:
    """f_d(t, dt, x, u, p, w) -> x(t + dt) by RK4 (or Euler) with ``substeps`` sub-steps, split at
    the model's events unless ``split_events`` is False (the branching form, see :class:`EventBranches`)."""
    branches = EventBranches(model, substeps, method, split_events)
    model_args = [model.t, ca.SX.sym("dt"), model.x, model.u, model.p, model.w]
    return branches.function("fd", model_args, ["t", "dt", "x", "u", "p", "w"], lambda fd: [fd(*model_args)],
                             ["x_next"], FUNCTION_OPTIONS)


def measurement_function(model: Model, name: str) -> ca.Function:
    """h(t, x, u, p, q) -> z for the named measurement."""
    meas = model.measurements[name]
    return ca.Function(f"h_{name}", [model.t, model.x, model.u, model.p, meas.q], [meas.h],
                       ["t", "x", "u", "p", "q"], ["z"], FUNCTION_OPTIONS)

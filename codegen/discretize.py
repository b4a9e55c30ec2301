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
import numpy as np

from symkf.models.base import Model

FUNCTION_OPTIONS = {"cse": True, "allow_duplicate_io_names": True}
#: The options of a function whose C is written once and called, not inlined into its callers.
CALLED_OPTIONS = dict(FUNCTION_OPTIONS, never_inline=True)
#: s: how far before an event the time argument is held on the segment that ends there (the
#: truth simulator uses the same inset, scenarios/launcher/truth.py).
EVENT_INSET = 1e-6
INTEGRATORS = ("rk4", "euler")
#: Float spacings of the latest event time that a float build's inset spans at least: 1e-6 s is
#: below float's resolution of time there (434.3 s: 3.1e-5 s), so t_e - 1e-6 would round to t_e and
#: the segment before the event would be integrated with the after-event dynamics (measured: a
#: 1.4 m/s speed defect in the launcher's step across burnout).
FLOAT_INSET_SPACINGS = 8


def event_inset(events, precision: str = "double") -> float:
    """How far before an event the segment ending there evaluates the dynamics: EVENT_INSET, or in
    a float build at least FLOAT_INSET_SPACINGS float spacings of the latest event time."""
    if precision != "float" or not len(events):
        return EVENT_INSET
    latest = np.float32(max(abs(float(e)) for e in events))
    return max(EVENT_INSET, FLOAT_INSET_SPACINGS * float(np.spacing(latest)))


def continuous_dynamics(model: Model) -> ca.Function:
    """f(t, x, u, p, w) -> dx/dt."""
    return ca.Function("f", [model.t, model.x, model.u, model.p, model.w], [model.f],
                       ["t", "x", "u", "p", "w"], ["xdot"], FUNCTION_OPTIONS)


def integrate(f, t, dt, x, u, p, w, substeps: int, method: str = "rk4", latest=None, y0=None):
    """``substeps`` steps of RK4 or explicit Euler from t to t + dt (no event handling).

    ``y0`` given: the increment form. The state is x + y, y starts at y0 and the increment y at
    t + dt is returned, so nothing is rounded at the magnitude of x (a float UKF's sigma-point
    deviations, codegen/families/kalman.py); without it, x(t + dt) as always.
    """
    if substeps < 1:
        raise ValueError(f"integrator substeps must be >= 1, got {substeps}")
    if method not in INTEGRATORS:
        raise ValueError(f"integrator: expected one of {INTEGRATORS}, got '{method}'")

    def rate(ti, yi):
        return f(ti if latest is None else ca.fmin(ti, latest), yi if y0 is None else x + yi, u, p, w)

    y = x if y0 is None else y0
    h = dt / substeps
    for i in range(substeps):
        ti = t + i * h
        k1 = rate(ti, y)
        if method == "euler":
            y = y + h * k1
            continue
        k2 = rate(ti + h / 2, y + h / 2 * k1)
        k3 = rate(ti + h / 2, y + h / 2 * k2)
        k4 = rate(ti + h, y + h * k3)
        y = y + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return y


def first_event_after(t, events, otherwise):
    """The first of the (increasing) event times strictly after t, else ``otherwise``."""
    result = otherwise
    for event in sorted(events, reverse=True):
        result = ca.if_else(t < event, event, result)
    return result


def split_times(t, dt, events, inset: float = EVENT_INSET):
    """The parts of a step split at t_e, the first event in (t, t + dt] (double form): (h1, latest,
    cut, h2) with [t, t + h1] (time held at most ``latest`` = t_e - inset) and [cut, cut + h2]."""
    end = t + dt
    event = first_event_after(t, events, end + 1.0)
    cut = ca.fmin(event, end)
    return cut - t, event - inset, cut, end - cut


def event_split_step(f, t, dt, x, u, p, w, events, substeps: int, method: str = "rk4", inset: float = EVENT_INSET,
                     lengths: bool = False, y0=None):
    """x(t + dt) integrated over [t, t_e] and [t_e, t + dt], t_e the first event in (t, t + dt)
    (with ``y0``: the increment form of :func:`integrate`).

    ``lengths``: compute the two parts' lengths as min(t_e - t, dt) and dt minus that, never from
    the absolute end time t + dt (a float build: at t = 433 s, float(t + dt) - t differs from dt by
    up to 1.5e-5 s, a 3e-4 relative error of every step, measured as a 6e-4 m/s speed bias per step
    in stage 2). Without it, the double build's form (cut - t, end - cut).
    """
    end = t + dt
    event = first_event_after(t, events, end + 1.0)
    if lengths:
        first = ca.fmin(event - t, dt)
        part = integrate(f, t, first, x, u, p, w, substeps, method, latest=event - inset, y0=y0)
        return integrate(f, t + first, dt - first, *((part,) if y0 is None else (x,)), u, p, w, substeps, method,
                         y0=None if y0 is None else part)
    cut = ca.fmin(event, end)
    part = integrate(f, t, cut - t, x, u, p, w, substeps, method, latest=event - inset, y0=y0)
    return integrate(f, cut, end - cut, *((part,) if y0 is None else (x,)), u, p, w, substeps, method,
                     y0=None if y0 is None else part)


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

    def __init__(self, model: Model, substeps: int, method: str = "rk4", split_events: bool = True,
                 precision: str = "double"):
        self.model, self.events = model, tuple(model.events) if split_events else ()
        self.substeps, self.method, self.precision = substeps, method, precision
        self.branches = self._branches(substeps, method, precision, increment=False)
        #: by name, the plain branch of each function :meth:`function` made with two branches (what
        #: it evaluates when no event lies in the step: the lockstep lanes, c_backend/flatten.py)
        self.plain_functions: dict[str, ca.Function] = {}
        #: the same branches in increment form: f_inc(t, dt, x, y0, u, p, w) -> y (:func:`integrate`)
        self.increment_branches = self._branches(substeps, method, precision, increment=True)

    def _branches(self, substeps: int, method: str, precision: str, increment: bool) -> tuple:
        model, f = self.model, continuous_dynamics(self.model)
        t, dt, x, u, p, w = model.t, ca.SX.sym("dt"), model.x, model.u, model.p, model.w
        y0 = ca.SX.sym("y0", model.nx) if increment else None
        args = [t, dt, x] + ([y0] if increment else []) + [u, p, w]
        names = ["t", "dt", "x"] + (["y0"] if increment else []) + ["u", "p", "w"]
        out, tag = (["y"], "fd_increment") if increment else (["x_next"], "fd")
        if not self.events:
            plain = integrate(f, t, dt, x, u, p, w, substeps, method, y0=y0)
            return (ca.Function(tag, args, [plain], names, out, FUNCTION_OPTIONS),)
        # double: (t + dt) - t, not dt: the split branch's first part when no event is inside (same
        # numbers); float: dt itself, as the split branch's lengths (event_split_step)
        lengths = precision == "float"
        plain = integrate(f, t, dt if lengths else (t + dt) - t, x, u, p, w, substeps, method, y0=y0)
        split = event_split_step(f, t, dt, x, u, p, w, self.events, substeps, method,
                                 event_inset(self.events, precision), lengths, y0)
        return (ca.Function(f"{tag}_plain", args, [plain], names, out, FUNCTION_OPTIONS),
                ca.Function(f"{tag}_split", args, [split], names, out, FUNCTION_OPTIONS))

    def segment_functions(self, name: str, outputs, output_names: list[str], options: dict):
        """Two SX Functions of one integration segment of a point x: ``<name>``(t0, h, x, u, p) ->
        ``outputs(x_end, x)`` over [t0, t0 + h], and ``<name>_capped``(t0, h, latest, x, u, p), its
        time argument held at most ``latest`` (the part of a split step before the event)."""
        model, f = self.model, continuous_dynamics(self.model)
        t0, h, latest = ca.SX.sym("t0"), ca.SX.sym("h"), ca.SX.sym("latest")
        x, u, p = ca.SX.sym("x", model.nx), ca.SX.sym("u", len(model.inputs)), ca.SX.sym("p", len(model.params))
        w = ca.DM.zeros(len(model.noises))
        free = integrate(f, t0, h, x, u, p, w, self.substeps, self.method)
        capped = integrate(f, t0, h, x, u, p, w, self.substeps, self.method, latest=latest)
        return (ca.Function(name, [t0, h, x, u, p], outputs(free, x), ["t0", "h", "x", "u", "p"], output_names, options),
                ca.Function(f"{name}_capped", [t0, h, latest, x, u, p], outputs(capped, x),
                            ["t0", "h", "latest", "x", "u", "p"], output_names, options))

    def function(self, name: str, inputs: list[ca.SX], input_names: list[str], outputs, output_names: list[str],
                 options: dict, branches: tuple | None = None, split=None, plain=None) -> ca.Function:
        """``name``(inputs) -> ``outputs(fd)`` with fd each branch in turn (of ``branches``, default
        :attr:`branches`): one SX Function without events, else an MX Function whose
        ``Function.conditional`` evaluates the plain branch, or the split one when an event lies in
        (t, t + dt] (``inputs`` start with t and dt).

        ``split`` and ``plain``, if given, build that branch instead: ``split(*mx_inputs)`` -> MX
        outputs (calls of existing functions: less C than a second inlined copy)."""
        branches = self.branches if branches is None else branches
        if len(branches) == 1:
            return ca.Function(name, inputs, outputs(branches[0]), input_names, output_names, options)
        sym = [ca.MX.sym(n, v.sparsity()) for n, v in zip(input_names, inputs)]
        if plain is None:
            plain_fn = ca.Function(f"{name}_plain", inputs, outputs(branches[0]), input_names, output_names, options)
        else:
            plain_fn = ca.Function(f"{name}_plain", sym, plain(*sym), input_names, output_names, options)
        if split is None:
            split_fn = ca.Function(f"{name}_split", inputs, outputs(branches[1]), input_names, output_names, options)
        else:
            split_fn = ca.Function(f"{name}_split", sym, split(*sym), input_names, output_names, options)
        switch = ca.Function.conditional(f"{name}_branch", [plain_fn], split_fn)
        self.plain_functions[name] = plain_fn
        flag = event_in_step(sym[0], sym[1], self.events)
        return ca.Function(name, sym, switch.call([flag, *sym]), input_names, output_names, options)


def discrete_step(model: Model, f, t, dt, x, u, p, w, substeps: int, method: str = "rk4",
                  split_events: bool = True, precision: str = "double"):
    """x(t + dt) as one SX expression, split at the model's events when asked (and it has any):
    branch-free, both parts always integrated (for kernels that inline f_d; :class:`EventBranches`
    evaluates only the part a step needs). A float build uses its own inset and part lengths."""
    if split_events and model.events:
        return event_split_step(f, t, dt, x, u, p, w, model.events, substeps, method,
                                event_inset(model.events, precision), lengths=precision == "float")
    return integrate(f, t, dt, x, u, p, w, substeps, method)


def discrete_dynamics(model: Model, substeps: int, method: str = "rk4", split_events: bool = True,
                      precision: str = "double") -> ca.Function:
    """f_d(t, dt, x, u, p, w) -> x(t + dt) by RK4 (or Euler) with ``substeps`` sub-steps, split at
    the model's events unless ``split_events`` is False (the branching form, see :class:`EventBranches`)."""
    branches = EventBranches(model, substeps, method, split_events, precision)
    model_args = [model.t, ca.SX.sym("dt"), model.x, model.u, model.p, model.w]
    return branches.function("fd", model_args, ["t", "dt", "x", "u", "p", "w"], lambda fd: [fd(*model_args)],
                             ["x_next"], FUNCTION_OPTIONS)


def measurement_function(model: Model, name: str) -> ca.Function:
    """h(t, x, u, p, q) -> z for the named measurement (its own noise v, if declared, at 0)."""
    meas = model.measurements[name]
    h = ca.substitute(meas.h, meas.v, ca.DM.zeros(meas.v.shape[0])) if meas.v.shape[0] else meas.h
    return ca.Function(f"h_{name}", [model.t, model.x, model.u, model.p, meas.q], [h],
                       ["t", "x", "u", "p", "q"], ["z"], FUNCTION_OPTIONS)


def noisy_measurement_function(model: Model, name: str) -> ca.Function:
    """h(t, x, u, p, q, v) -> z with the measurement's own noise v (Model.measurement_noise)."""
    meas = model.measurements[name]
    return ca.Function(f"h_{name}_noisy", [model.t, model.x, model.u, model.p, meas.q, meas.v], [meas.h],
                       ["t", "x", "u", "p", "q", "v"], ["z"], FUNCTION_OPTIONS)


def exact_step_function(model: Model) -> ca.Function:
    """The model's declared exact step φ(t, dt, x, u, p, w) (Model.set_discrete_step)."""
    dt, step = model.discrete_step
    return ca.Function("fd_exact", [model.t, dt, model.x, model.u, model.p, model.w], [step],
                       ["t", "dt", "x", "u", "p", "w"], ["x_next"], FUNCTION_OPTIONS)

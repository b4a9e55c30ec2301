"""The kernel framework every filter family builds on (families live in ``codegen/families/``).

- :class:`Symbols`: the canonical kernel arguments of a model (t, dt, x, P, u, p, Q, per
  measurement q, z, mask, R, ...), one SX symbol and one :class:`~symkf.codegen.spec.Arg` each.
- :class:`ModelFunctions`: the model's f_d, F = df_d/dx, h and H = dh/dx as CasADi Functions,
  generated once and called by every family's kernels.
- :func:`make_kernel` (the one way to declare a kernel) and :func:`compose_step` (predict then
  update as one kernel); :func:`model_kernels` for the stand-alone model functions.
- Shared update algebra: masked noise, wrapped masked innovation, keep-on-failure outputs.
- :data:`FAMILIES` / :func:`register_family`: a model asks for families by name.

Every update takes an availability ``mask`` (1 = use, 0 = ignore): a masked component's
innovation is zero, its row of H and its sigma-point deviations are zero and its noise variance
is replaced by 1, so it contributes exactly nothing; an all-masked update returns x and P unchanged.
A failed factorisation returns a status code and the inputs x, P unchanged.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import casadi as ca

from symkf.models.base import Model
from . import linalg
from .discretize import (FUNCTION_OPTIONS, INTEGRATORS, EventBranches, continuous_dynamics, discrete_step, split_times,
                         measurement_function)
from .spec import (STATUS_GATED, STATUS_NONFINITE, STATUS_NOT_PD, Arg, CodegenConfig, ConfigError, Family, FilterSpec,
                   Kernel, register_options)


class Symbols:
    """The canonical kernel arguments of a model: one SX symbol and one Arg description each."""

    def __init__(self, model: Model):
        n, units = model.nx, [v.unit for v in model.states]
        state_units = ", ".join(units)
        self.model = model
        self.sym: dict[str, ca.SX] = {
            "t": model.t, "dt": ca.SX.sym("dt"), "x": ca.SX.sym("x", n), "P": ca.SX.sym("P", n, n),
            "u": ca.SX.sym("u", len(model.inputs)), "p": ca.SX.sym("p", len(model.params)),
            "Q": ca.SX.sym("Q", n, n), "kappa": ca.SX.sym("kappa")}
        self.arg: dict[str, Arg] = {
            "t": Arg("t", (1, 1), "s", "time at the start of the step"),
            "dt": Arg("dt", (1, 1), "s", "step length"),
            "x": Arg("x", (n, 1), state_units, "state estimate " + str(model.state_names())),
            "P": Arg("P", (n, n), "state units squared", "state error covariance (symmetric)"),
            "u": Arg("u", (len(model.inputs), 1), ", ".join(v.unit for v in model.inputs) or "-",
                     "known inputs " + str([v.name for v in model.inputs])),
            "p": Arg("p", (len(model.params), 1), ", ".join(v.unit for v in model.params) or "-",
                     "runtime parameters " + str([v.name for v in model.params])),
            "Q": Arg("Q", (n, n), "state units squared per second",
                     "process noise power spectral density (discrete: Q dt)"),
            "kappa": Arg("kappa", (1, 1), "-", "UKF scaling parameter (n + kappa > 0)"),
            "status": Arg("status", (1, 1), "-", "0 on success, else a SYMKF_ERR_* code"),
        }

    def measurement(self, name: str) -> tuple[dict[str, ca.SX], dict[str, Arg]]:
        """Symbols and Args of one measurement's inputs and diagnostics. A quaternion measurement
        (``Model.measurement(..., quaternion=True)``) has one mask entry for the whole quaternion and
        a 3-vector innovation; a measurement with its own noise v has R = cov(v) (nv x nv)."""
        meas = self.model.measurements[name]
        m, units = meas.size, ", ".join(v.unit for v in meas.outputs)
        n_mask, n_y = (1, 3) if meas.quaternion else (m, m)
        n_r = meas.v.shape[0] or n_y
        sym = {"q": ca.SX.sym("q", meas.q.shape[0]), "z": ca.SX.sym("z", m),
               "mask": ca.SX.sym("mask", n_mask), "R": ca.SX.sym("R", n_r, n_r), "gate": ca.SX.sym("gate", n_y)}
        innovation = ("error of z relative to h(x) in the filter's chart (masked: 0)" if meas.quaternion
                      else "innovation z - h(x) (angles wrapped, masked entries 0)")
        args = {
            "q": Arg("q", (meas.q.shape[0], 1), ", ".join(v.unit for v in meas.params) or "-",
                     f"parameters of measurement '{name}' " + str([v.name for v in meas.params])),
            "z": Arg("z", (m, 1), units, f"measurement '{name}' " + str([v.name for v in meas.outputs])),
            "mask": Arg("mask", (n_mask, 1), "-", "1: use the quaternion measurement, 0: none" if meas.quaternion
                        else "availability per component: 1 use, 0 ignore"),
            "R": Arg("R", (n_r, n_r), ", ".join(f"({v.unit})^2" for v in meas.noise) or "measurement units squared",
                     f"covariance of the measurement noise {[v.name for v in meas.noise]}" if meas.noise
                     else "measurement noise covariance"),
            "gate": Arg("gate", (n_y, 1), "-", "chi-square gate: gate[k-1] bounds y^T S^-1 y when k innovation "
                        "components are used; 0 = no gate"),
            "y": Arg("y", (n_y, 1), "-" if meas.quaternion else units, innovation),
            "S": Arg("S", (n_y, n_y), "-" if meas.quaternion else "measurement units squared", "innovation covariance"),
        }
        return sym, args


#: How a filter family discretises the model (codegen config keys ``<family>_<field>``; the
#: defaults are the model's: RK4 with ``rk4_substeps``, exact Jacobian, events split).
COVARIANCE_PROPAGATIONS = ("jacobian", "linear")


@dataclass(frozen=True)
class Discretisation:
    """One filter family's discretisation of the dynamics.

    Attributes:
        integrator: "rk4" or "euler" for the state propagation x(t + dt) = f_d(t, dt, x).
        substeps: integrator sub-steps per filter step.
        covariance: "jacobian" (F = d f_d / d x, exact for the discrete map) or "linear"
            (Phi = I + A dt with A = d f / d x at the step start, the classical first-order form).
        split_events: cut a step at the model's events (codegen/discretize.py).
    """

    integrator: str = "rk4"
    substeps: int = 1
    covariance: str = "jacobian"
    split_events: bool = True

    @classmethod
    def for_family(cls, config: CodegenConfig, family: str) -> "Discretisation":
        """The config's ``<family>_integrator/_substeps/_covariance/_split_events`` over its defaults."""
        base = cls(substeps=config.rk4_substeps, split_events=bool(config.get("split_events", True)))
        chosen = cls(**{name: config.get(f"{family}_{name}", getattr(base, name))
                        for name in cls.__dataclass_fields__})
        if chosen.integrator not in INTEGRATORS or chosen.covariance not in COVARIANCE_PROPAGATIONS:
            raise ConfigError(f"{family}: integrator must be one of {INTEGRATORS} and covariance one of "
                             f"{COVARIANCE_PROPAGATIONS}; got '{chosen.integrator}', '{chosen.covariance}'")
        if int(chosen.substeps) != chosen.substeps or chosen.substeps < 1:
            raise ConfigError(f"{family}: substeps must be an integer >= 1, got {chosen.substeps}")
        return chosen

    @property
    def suffix(self) -> str:
        """A C-safe tag naming this discretisation (e.g. '_euler1_lin')."""
        return (f"_{self.integrator}{self.substeps}" + ("_lin" if self.covariance == "linear" else "")
                + ("" if self.split_events else "_nosplit"))


@dataclass(frozen=True)
class Propagation:
    """A family's propagation functions: f_d, its transition matrix, both, and f_d over sigma points.

    Each branches on the model's events (:class:`~symkf.codegen.discretize.EventBranches`): the
    generated C integrates a step that holds no event once, and only a step that holds one twice.
    ``fd_inline`` is the branch-free f_d (SX, both parts always integrated), for families that
    inline f_d in their kernels.
    """

    fd: ca.Function
    fd_inline: ca.Function
    jac_fd: ca.Function
    fd_and_jac: ca.Function
    branches: EventBranches
    prefix: str
    point_functions: dict = field(default_factory=dict, compare=False, repr=False)   # fd_at_points, increments

    def fd_at_points(self, tag: str, inputs: dict[str, ca.SX], points) -> ca.Function:
        """``<prefix>_fd_<tag>``(t, dt, *inputs, u, p) -> f_d at each of ``points(*inputs)`` (a list
        of state vectors), as the columns of one matrix: one function per event branch, called,
        not inlined. The points are formed inside, so CSE sees what they share: every term of f_d
        that depends on time only (thrust, mass, guidance) is evaluated once, not once per point,
        and so is a term of a state component that several points leave unchanged."""
        if tag not in self.point_functions:
            model = self.branches.model
            t, dt = model.t, ca.SX.sym("dt")
            u, p = ca.SX.sym("u", len(model.inputs)), ca.SX.sym("p", len(model.params))
            w = ca.DM.zeros(len(model.noises))
            args, names = [t, dt, *inputs.values(), u, p], ["t", "dt", *inputs, "u", "p"]
            # the split branch (steps holding an event: 4 a flight) calls f_d point by point
            self.point_functions[tag] = self.branches.function(
                f"{self.prefix}_fd_{tag}", args, names,
                lambda fd: [ca.horzcat(*[fd(t, dt, pt, u, p, w) for pt in points(*inputs.values())])], ["X"],
                dict(FUNCTION_OPTIONS, never_inline=True),
                split=lambda t, dt, *rest: [ca.horzcat(*[self.fd(t, dt, pt, rest[-2], rest[-1])
                                                        for pt in points(*rest[:-2])])])
        return self.point_functions[tag]

    def increment_columns(self, k: int) -> ca.Function:
        """``<prefix>_increment_columns<k>``(t, dt, x, D, u, p) -> Y: column i of Y is the step of
        x + D[:, i] as an increment of x (codegen/discretize.py ``integrate``'s increment form), one
        function per event branch like :meth:`fd_at_points`. A float UKF propagates its sigma-point
        offsets with it, never forming differences of numbers of the state's magnitude."""
        if ("increment", k) not in self.point_functions:
            model = self.branches.model
            t, dt, x, D = model.t, ca.SX.sym("dt"), ca.SX.sym("x", model.nx), ca.SX.sym("D", model.nx, k)
            u, p = ca.SX.sym("u", len(model.inputs)), ca.SX.sym("p", len(model.params))
            w = ca.DM.zeros(len(model.noises))
            self.point_functions["increment", k] = self.branches.function(
                f"{self.prefix}_increment_columns{k}", [t, dt, x, D, u, p], ["t", "dt", "x", "D", "u", "p"],
                lambda inc: [ca.horzcat(*[inc(t, dt, x, D[:, i], u, p, w) for i in range(k)])], ["Y"],
                dict(FUNCTION_OPTIONS, never_inline=True), self.branches.increment_branches)
        return self.point_functions["increment", k]


class ModelFunctions:
    """The model's own functions, each generated once in C and *called* by the filter kernels.

    f_d, its Jacobian, h and its Jacobian are CasADi functions marked ``never_inline``: the C of
    each is written once and called. A family whose configured :class:`Discretisation` differs
    from the model's default gets its own f_d variant from :meth:`for_filter`.
    """

    def __init__(self, model: Model, config: CodegenConfig):
        self.config, self.model = config, model
        prefix = model.name
        options = dict(FUNCTION_OPTIONS, never_inline=True)
        self.zero_w = ca.DM.zeros(len(model.noises))
        default = Discretisation(substeps=config.rk4_substeps, split_events=bool(config.get("split_events", True)))
        self._propagations: dict[Discretisation, Propagation] = {}
        main = self._propagation(default, "")
        self.fd, self.fd_inline, self.jac_fd, self.fd_and_jac = main.fd, main.fd_inline, main.jac_fd, main.fd_and_jac
        self.noise_gain = noise_gain(model) if model.noises else None
        self.h, self.jac_h, self.h_and_jac = {}, {}, {}
        for name in model.measurements:
            h = measurement_function(model, name)
            ht, hx, hu, hp, hq = h.sx_in()
            z = h(ht, hx, hu, hp, hq)
            hargs, hnames = [ht, hx, hu, hp, hq], ["t", "x", "u", "p", "q"]
            self.h[name] = ca.Function(f"{prefix}_h_{name}", hargs, [z], hnames, ["z"], options)
            # z and H share the measurement's terms (trigonometry of the station and the state);
            # H alone calls that function (one copy of the Jacobian's C). H keeps its structural
            # zeros (a radar sees only the position states): the EKF update's products skip them,
            # the same numbers as with explicit zeros (x + 0 y = x); jac_h is H densified.
            both = ca.Function(f"{prefix}_h_and_jac_{name}", hargs, [z, ca.jacobian(z, hx)],
                               hnames, ["z", "H"], options)
            mx = [ca.MX.sym(n, *v.shape) for n, v in zip(hnames, hargs)]
            self.h_and_jac[name] = both
            self.jac_h[name] = ca.Function(f"{prefix}_jac_h_{name}", mx, [ca.densify(both(*mx)[1])], hnames, ["H"],
                                           options)

    def for_filter(self, family: str) -> Propagation:
        """The propagation functions of one family, per the config's ``<family>_*`` keys."""
        chosen = Discretisation.for_family(self.config, family)
        return self._propagation(chosen, chosen.suffix)

    def _propagation(self, d: Discretisation, suffix: str) -> Propagation:
        if d in self._propagations:
            return self._propagations[d]
        model, prefix = self.model, self.model.name + suffix
        options = dict(FUNCTION_OPTIONS, never_inline=True)
        branches = EventBranches(model, int(d.substeps), d.integrator, d.split_events, self.config.precision)
        t, dt = model.t, ca.SX.sym("dt")
        x, u, p = ca.SX.sym("x", model.nx), ca.SX.sym("u", len(model.inputs)), ca.SX.sym("p", len(model.params))
        args, names = [t, dt, x, u, p], ["t", "dt", "x", "u", "p"]

        def step(fd):
            return fd(t, dt, x, u, p, self.zero_w)

        pattern = transition_pattern(step(branches.branches[0]), x)

        def transition(fd):
            if d.covariance == "jacobian":
                return on_pattern(ca.jacobian(step(fd), x), pattern)
            xdot = continuous_dynamics(model)(t, x, u, p, self.zero_w)     # Phi = I + A dt, A = df/dx at (t, x)
            return ca.SX.eye(model.nx) + ca.densify(ca.jacobian(xdot, x)) * dt

        # f_d and F together share the primal evaluation (the EKF prediction needs both); F alone
        # calls that function (one copy of the Jacobian's C)
        fd_and_jac = branches.function(f"{prefix}_fd_and_jac", args, names, lambda fd: [step(fd), transition(fd)],
                                       ["x", "F"], options, **self._segment_calls(branches, d, prefix, pattern))
        mx = [ca.MX.sym(n, *v.shape) for n, v in zip(names, args)]
        jac_fd = ca.Function(f"{prefix}_jac_fd", mx, [ca.densify(fd_and_jac(*mx)[1])], names, ["F"], options)
        made = Propagation(
            branches.function(f"{prefix}_fd", args, names, lambda fd: [step(fd)], ["x"], options),
            ca.Function(f"{prefix}_fd_inline", args, [discrete_step(model, continuous_dynamics(model), *args, self.zero_w,
                        int(d.substeps), d.integrator, d.split_events, self.config.precision)], names, ["x"],
                        FUNCTION_OPTIONS),
            jac_fd, fd_and_jac, branches, prefix)
        self._propagations[d] = made
        return made


    @staticmethod
    def _segment_calls(branches: EventBranches, d: Discretisation, prefix: str, pattern: ca.Sparsity) -> dict:
        """For an exact Jacobian of a model with events: f_d and F of both branches from calls of
        one segment function and its time-capped twin (not inlined twice): the plain step is one
        segment over h = (t + dt) - t, the split step two, F = F2 F1 (chain rule: the same F up
        to the order of round-off; the plain branch's numbers are unchanged)."""
        if d.covariance != "jacobian" or len(branches.branches) == 1 or branches.precision == "float":
            return {}       # (a float build's split step has its own part lengths: inlined as is)
        free, capped = branches.segment_functions(
            f"{prefix}_segment_and_jac", lambda x_end, x: [x_end, on_pattern(ca.jacobian(x_end, x), pattern)], ["x", "F"],
            dict(FUNCTION_OPTIONS, never_inline=True))

        def plain(t, dt, x, u, p):
            return free.call([t, (t + dt) - t, x, u, p])

        def split(t, dt, x, u, p):
            h1, latest, cut, h2 = split_times(t, dt, branches.events)
            x_cut, F1 = capped.call([t, h1, latest, x, u, p])
            x_end, F2 = free.call([cut, h2, x_cut, u, p])
            return [x_end, ca.project(ca.mtimes(F2, F1), pattern)]
        return {"plain": plain, "split": split}


def transition_pattern(x_next: ca.SX, x: ca.SX) -> ca.Sparsity:
    """The structural nonzeros of F = d f_d / d x that every event branch shares: those of one
    step S and of two steps S S (a split step's F2 F1). A state nothing depends on (the launcher's
    longitude) keeps F's column of the identity, and F P F^T skips its zeros (the same numbers as
    with explicit zeros: x + 0 y = x)."""
    S = ca.DM.ones(ca.jacobian_sparsity(x_next, x))
    return (S + S @ S).sparsity()


def on_pattern(J, pattern: ca.Sparsity):
    """J on the shared ``pattern`` (explicit zeros where J has none); J must not reach outside it."""
    if not J.sparsity().is_subset(pattern):
        raise ValueError("a branch's Jacobian has nonzeros outside the pattern of one or two steps")
    return ca.project(J, pattern)


def noise_gain(model: Model) -> ca.Function:
    """G(t, x, u, p) = df/dw at w = 0 (n x nw): how the process noises w enter the dynamics."""
    f = continuous_dynamics(model)
    w = ca.SX.sym("w", len(model.noises))
    G = ca.jacobian(f(model.t, model.x, model.u, model.p, w), w)
    G = ca.densify(ca.substitute(G, w, ca.DM.zeros(len(model.noises))))
    return ca.Function(f"{model.name}_noise_gain", [model.t, model.x, model.u, model.p], [G],
                       ["t", "x", "u", "p"], ["G"], FUNCTION_OPTIONS)


def make_kernel(name: str, doc: str, symbols: Symbols, extra_sym: dict, extra_arg: dict,
            inputs: list[str], outputs: list[tuple[str, ca.SX]], carried=(), per_step=()) -> Kernel:
    sym = {**symbols.sym, **extra_sym}
    args = {**symbols.arg, **extra_arg}
    out_names = [o for o, _ in outputs]
    function = ca.Function(f"{symbols.model.name}_k_{name}", [sym[i] for i in inputs],
                           [ca.densify(expr) for _, expr in outputs], inputs, out_names, FUNCTION_OPTIONS)
    return Kernel(name, function, doc, tuple(args[i] for i in inputs),
                  tuple(args[o] if o in args else Arg(o, tuple(e.shape)) for o, e in outputs),
                  tuple(carried), tuple(per_step))


# ---------------------------------------------------------------------- model functions
def model_kernels(model: Model, symbols: Symbols, fns: ModelFunctions) -> list[Kernel]:
    """f, f_d, F = df_d/dx, and h, H = dh/dx for every measurement (those in
    ``model.generic_kernels``: a model whose filters need none of them can leave them out)."""
    s = symbols.sym
    f = continuous_dynamics(model)
    step_args = (s["t"], s["dt"], s["x"], s["u"], s["p"])
    kernels = [
        make_kernel("f", "Continuous dynamics dx/dt = f(t, x, u, p).", symbols, {}, {},
                ["t", "x", "u", "p"], [("xdot", f(s["t"], s["x"], s["u"], s["p"], fns.zero_w)), ("status", ca.SX(0))]),
        make_kernel("fd", "Discrete dynamics: RK4 from t to t + dt.", symbols, {}, {},
                ["t", "dt", "x", "u", "p"], [("x", fns.fd(*step_args)), ("status", ca.SX(0))]),
        make_kernel("jac_fd", "State-transition Jacobian F = d f_d / d x (derived by CasADi).", symbols, {}, {},
                ["t", "dt", "x", "u", "p"], [("F", fns.jac_fd(*step_args)), ("status", ca.SX(0))]),
    ]
    for name in model.measurements:
        msym, marg = symbols.measurement(name)
        meas_args = (s["t"], s["x"], s["u"], s["p"], msym["q"])
        kernels += [
            make_kernel(f"h_{name}", f"Measurement '{name}': z = h(t, x, u, p, q).", symbols, msym, marg,
                    ["t", "x", "u", "p", "q"], [("z", fns.h[name](*meas_args)), ("status", ca.SX(0))]),
            make_kernel(f"jac_h_{name}", f"Measurement Jacobian H = dh/dx of '{name}' (derived by CasADi).",
                    symbols, msym, marg, ["t", "x", "u", "p", "q"],
                    [("H", fns.jac_h[name](*meas_args)), ("status", ca.SX(0))]),
        ]
    wanted = _generic_names(model)
    return [k for k in kernels if k.name in wanted]


def _generic_names(model: Model) -> set[str]:
    wanted = set(model.generic_kernels)
    names = {"f", "fd", "jac_fd"} & wanted
    for name in model.measurements:
        names |= {f"h_{name}"} if "h" in wanted else set()
        names |= {f"jac_h_{name}"} if "jac_h" in wanted else set()
    return names


# ---------------------------------------------------------------------- shared update algebra
def masked_noise(R: ca.SX, mask: ca.SX) -> ca.SX:
    """R with masked rows/columns replaced by the identity's (keeps S positive definite)."""
    m = R.shape[0]
    return ca.vertcat(*[ca.horzcat(*[
        R[i, j] * mask[i] * mask[j] + (1 - mask[i]) * (1.0 if i == j else 0.0) for j in range(m)])
        for i in range(m)])


def innovation(z: ca.SX, z_pred: ca.SX, mask: ca.SX, wrap: tuple[bool, ...]) -> ca.SX:
    """z - z_pred, angles wrapped; masked components are exactly 0 even if z is NaN there."""
    rows = []
    for i, is_angle in enumerate(wrap):
        d = linalg.select(mask[i] > 0.5, z[i], z_pred[i]) - z_pred[i]      # a masked NaN enters no arithmetic
        rows.append(linalg.select(mask[i] > 0.5, linalg.wrap_angle(d) if is_angle else d, 0))
    return ca.vertcat(*rows)


def keep_on_failure(ok: ca.SX, new: list[ca.SX], old: list[ca.SX], failure_code: int) -> list[ca.SX]:
    kept = [linalg.select(ok, a, b) for a, b in zip(new, old)]
    return kept + [linalg.select(ok, 0, failure_code)]


def gated(gate: ca.SX, mask: ca.SX, nis: ca.SX) -> ca.SX:
    """1 if the normalised innovation squared ``nis`` = y^T S^-1 y exceeds the gate for the number
    k of used components (``gate[k-1]``; a gate <= 0 is off), else 0."""
    used = ca.sum1(mask)
    threshold = sum((ca.if_else(used == i + 1, gate[i], 0) for i in range(gate.shape[0])), 0)
    return (threshold > 0) * (nis > threshold)


def all_finite(values: list[ca.SX]) -> ca.SX:
    """1 if every entry of every value is finite, else 0: |sum of the entries x 2^-1000| < Inf (a NaN
    or an infinite entry makes the sum NaN or infinite; scaled finite entries cannot overflow it)."""
    total = ca.SX(0)
    for value in values:
        for i in range(value.numel()):
            total = total + value[i] * FINITE_SCALE
    return ca.fabs(total) < ca.inf


#: 2^-1000: scaled, any finite input has |v| < 2^24, so a sum of fewer than 2^999 of them is
#: finite; a NaN or an infinity makes the sum NaN or infinite. One multiply-add per entry.
FINITE_SCALE = 2.0 ** -1000


#: Argument order of every generated filter function (a kernel uses the subset it needs).
CANONICAL_ORDER = ("t", "dt", "x", "P", "u", "p", "Q", "q", "z", "mask", "R", "gate", "kappa")


def compose_step(name: str, predict: Kernel, update: Kernel) -> Kernel:
    """predict(t, dt) then update at t + dt, as one kernel that calls the two (no code copied).

    Inputs are the union of both kernels' inputs (predict's order first); outputs are the
    update's. If either part fails, x and P come back unchanged with the first failure's code.
    """
    inputs = list(predict.inputs) + [a for a in update.inputs if a.name not in {b.name for b in predict.inputs}]
    inputs.sort(key=lambda a: CANONICAL_ORDER.index(a.name) if a.name in CANONICAL_ORDER else len(CANONICAL_ORDER))
    sym = {a.name: ca.MX.sym(a.name, *a.shape) for a in inputs}
    pred = predict.function.call({a.name: sym[a.name] for a in predict.inputs})
    upd_args = {a.name: sym[a.name] for a in update.inputs}
    upd_args.update(t=sym["t"] + sym["dt"], x=pred["x"], P=pred["P"])
    upd = update.function.call(upd_args)
    failed_early = pred["status"] != 0
    outputs = []
    for a in update.outputs:
        value = upd[a.name]
        if a.name in ("x", "P"):
            value = ca.if_else(failed_early, sym[a.name], value)
        elif a.name == "status":
            value = ca.if_else(failed_early, pred["status"], value)
        outputs.append(value)
    model = predict.function.name().split("_k_")[0]
    function = ca.Function(f"{model}_k_{name}", [sym[a.name] for a in inputs], outputs,
                           [a.name for a in inputs], [a.name for a in update.outputs],
                           {"allow_duplicate_io_names": True})
    doc = f"{predict.doc.split(' (')[0]}; then {update.doc.replace(' at time t ', ' at t + dt ')} Both in one call."
    return Kernel(name, function, doc, tuple(inputs), update.outputs, carried=("x", "P"),
                  per_step=tuple(a.name for a in inputs if a.name in ("t", "dt", "u", "q", "z", "mask")),
                  parts=(predict.name, update.name))


def update_status(ok: ca.SX, is_gated: ca.SX, inputs_finite: ca.SX) -> ca.SX:
    """NONFINITE if an input is NaN/Inf, else NOT_PD if a factorisation failed, else GATED or 0."""
    status = linalg.select(is_gated, STATUS_GATED, 0)
    status = linalg.select(ok, status, STATUS_NOT_PD)
    return linalg.select(inputs_finite, status, STATUS_NONFINITE)


def update_outputs(update, x_old, P_old, gate, mask, inputs_finite):
    """x, P (unchanged unless the update succeeded and passed the gate), y, S, status."""
    x_new, P_new, y, S, ok, nis = update
    is_gated = gated(gate, mask, nis)
    keep = ok * (1 - is_gated) * inputs_finite
    x_out, P_out = (linalg.select(keep, new, old) for new, old in ((x_new, x_old), (P_new, P_old)))
    return [("x", x_out), ("P", P_out), ("y", y), ("S", S), ("status", update_status(ok, is_gated, inputs_finite))]


def masked_finite(z: ca.SX, mask: ca.SX) -> ca.SX:
    """1 if every used component of z is finite (masked components may be NaN)."""
    flag = ca.SX(1)
    for i in range(z.shape[0]):
        flag = flag * ((mask[i] < 0.5) + (mask[i] >= 0.5) * linalg.finite_flag(z[i]))
    return flag


def filter_spec(name: str, algorithm: str, kernels: list[Kernel], measurements, **fields) -> FilterSpec:
    """The spec of filter ``name`` whose kernels follow the naming rule ``<name>_predict``,
    ``<name>_update_<measurement>``, ``<name>_step_<measurement>`` (those present in ``kernels``)."""
    names = {k.name for k in kernels}
    predict = f"{name}_predict" if f"{name}_predict" in names else ""
    update = {m: f"{name}_update_{m}" for m in measurements if f"{name}_update_{m}" in names}
    step = {m: f"{name}_step_{m}" for m in measurements if f"{name}_step_{m}" in names}
    if not step:
        raise ValueError(f"filter '{name}': no kernel named {name}_step_<measurement> among {sorted(names)}")
    return FilterSpec(name, algorithm, predict, update, step, **fields)


FamilyBuilder = Callable[[Model, Symbols, ModelFunctions], "Family"]

#: Filter families a model can ask for by name in ``Model.filters``. Each lives in
#: ``codegen/families/<algorithm>.py`` and calls :func:`register_family` when imported;
#: ``symkf.codegen.families`` imports them all.
FAMILIES: dict[str, FamilyBuilder] = {}
#: Families whose kernels call the bundle's longest compile (the UKF: f_d at 2n + 1 sigma points,
#: one function); a build generates them before the other families, so that unit compiles first.
LONG_COMPILE: set[str] = set()


def register_family(name: str, builder: FamilyBuilder, long_compile: bool = False) -> FamilyBuilder:
    """Make a filter family available to models by name (``long_compile``: see :data:`LONG_COMPILE`)."""
    if name in FAMILIES and FAMILIES[name] is not builder:
        raise ValueError(f"filter family '{name}' is registered twice")
    FAMILIES[name] = builder
    if long_compile:
        LONG_COMPILE.add(name)
    register_options(*(f"{name}_{option}" for option in Discretisation.__dataclass_fields__))
    return builder

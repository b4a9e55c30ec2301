"""The model's own functions as every filter family uses them, and the families' kernel arguments.

- :class:`Symbols`: the canonical kernel arguments of a model (t, dt, x, P, u, p, Q, per
  measurement q, z, mask, R, ...), one SX symbol and one :class:`~symkf.codegen.spec.Arg` each.
- :class:`Discretisation`: how one filter family discretises the dynamics (its typed options
  ``<family>_integrator/_substeps/_covariance/_split_events``).
- :class:`ModelFunctions`: the model's f_d, F = df_d/dx, h and H = dh/dx as CasADi Functions,
  generated once and called by every family's kernels; :class:`Propagation`: one
  discretisation's f_d and F (events branched, codegen/discretize.py).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import casadi as ca

from symkf.models.base import Model
from .discretize import (CALLED_OPTIONS, FUNCTION_OPTIONS, INTEGRATORS, EventBranches, continuous_dynamics,
                         discrete_step, measurement_function, split_times)
from .spec import Arg, CodegenConfig, ConfigError, declare_options, option


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


#: The covariance propagations a family can choose (:attr:`Discretisation.covariance`).
COVARIANCE_PROPAGATIONS = ("jacobian", "linear")


@dataclass(frozen=True)
class EventOptions:
    """How every family's step treats the model's events (codegen/discretize.py)."""

    split_events: bool = option(True, "cut a step at the model's events (every family's default)")


declare_options(EventOptions, "symkf.codegen.model_functions")


@dataclass(frozen=True)
class Discretisation:
    """One filter family's discretisation of the dynamics: its options ``<family>_<field>``
    (declared for every family by ``register_family``); the defaults are the model's: RK4 with
    ``rk4_substeps``, exact Jacobian, events split as ``split_events``.

    Attributes:
        integrator: "rk4" or "euler" for the state propagation x(t + dt) = f_d(t, dt, x).
        substeps: integrator sub-steps per filter step.
        covariance: "jacobian" (F = d f_d / d x, exact for the discrete map) or "linear"
            (Phi = I + A dt with A = d f / d x at the step start, the classical first-order form).
        split_events: cut a step at the model's events (codegen/discretize.py).
    """

    integrator: str = option("rk4", "the family's integrator of f_d: 'rk4' or 'euler'")
    substeps: int = option(1, "the family's integrator sub-steps per filter step (default: rk4_substeps)")
    covariance: str = option("jacobian", "the family's transition matrix: 'jacobian' (F = d f_d / d x) or 'linear' "
                                         "(Phi = I + A dt)")
    split_events: bool = option(True, "the family's step cut at the model's events (default: split_events)")

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
    #: by name, each weight switch of :meth:`fd_at_points_weighted` and its centre-free branch
    #: (what it calls when the centre weight is 0: the lockstep lanes, c_backend/flatten.py)
    weight_switches: dict = field(default_factory=dict, compare=False, repr=False)

    def fd_at_points(self, tag: str, inputs: dict[str, ca.SX], points, centre_free: bool = False) -> ca.Function:
        """``<prefix>_fd_<tag>``(t, dt, *inputs, u, p) -> f_d at each of ``points(*inputs)`` (a list
        of state vectors), as the columns of one matrix: one function per event branch, called,
        not inlined. The points are formed inside, so CSE sees what they share: every term of f_d
        that depends on time only (thrust, mass, guidance) is evaluated once, not once per point,
        and so is a term of a state component that several points leave unchanged.
        ``centre_free``: the first column is the first point itself, not propagated (see
        :meth:`fd_at_points_weighted`)."""
        if (tag, centre_free) not in self.point_functions:
            model = self.branches.model
            t, dt = model.t, ca.SX.sym("dt")
            u, p = ca.SX.sym("u", len(model.inputs)), ca.SX.sym("p", len(model.params))
            w = ca.DM.zeros(len(model.noises))
            args, names = [t, dt, *inputs.values(), u, p], ["t", "dt", *inputs, "u", "p"]

            def columns(step, pts):
                """The points, each through ``step`` (but the first with ``centre_free``), as columns."""
                kept = pts[:1] if centre_free else []
                return [ca.horzcat(*kept, *[step(pt) for pt in pts[len(kept):]])]
            # the split branch (steps holding an event: 4 a flight) calls f_d point by point
            self.point_functions[tag, centre_free] = self.branches.function(
                f"{self.prefix}_fd_{tag}", args, names,
                lambda fd: columns(lambda pt: fd(t, dt, pt, u, p, w), points(*inputs.values())), ["X"], CALLED_OPTIONS,
                split=lambda t_, dt_, *rest: columns(lambda pt: self.fd(t_, dt_, pt, rest[-2], rest[-1]),
                                                     points(*rest[:-2])))
        return self.point_functions[tag, centre_free]

    def fd_at_points_weighted(self, tag: str, inputs: dict[str, ca.SX], points) -> ca.Function:
        """``<prefix>_fd_<tag>_weighted``(w0, t, dt, *inputs, u, p): :meth:`fd_at_points`, except that
        with w0 == 0 (the first point's weight exactly zero: a UKF with kappa = 0) the first point is
        not propagated and its column is the point itself. A caller multiplies that column by w0, so
        it adds the same exact zeros either way: the same numbers, one point fewer to integrate. The
        generated C picks the variant at call time (``Function.conditional``: an ``if`` around calls)."""
        key = ("weighted", tag)
        if key not in self.point_functions:
            full = self.fd_at_points(tag, inputs, points)
            free = self.fd_at_points(f"{tag}_centre_free", inputs, points, centre_free=True)
            switch = ca.Function.conditional(f"{self.prefix}_fd_{tag}_by_weight", [free], full)
            self.weight_switches[switch.name()] = free
            w0, sym = ca.MX.sym("w0"), full.mx_in()
            self.point_functions[key] = ca.Function(
                f"{self.prefix}_fd_{tag}_weighted", [w0, *sym], switch.call([w0 != 0, *sym]),
                ["w0", *full.name_in()], ["X"], CALLED_OPTIONS)
        return self.point_functions[key]

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
                CALLED_OPTIONS, self.branches.increment_branches)
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
        options = CALLED_OPTIONS
        self.zero_w = ca.DM.zeros(len(model.noises))
        default = Discretisation(substeps=config.rk4_substeps, split_events=bool(config.get("split_events", True)))
        self._propagations: dict[Discretisation, Propagation] = {}
        main = self._propagation(default, "")
        self.fd, self.fd_inline, self.jac_fd, self.fd_and_jac = main.fd, main.fd_inline, main.jac_fd, main.fd_and_jac
        self.noise_gain = noise_gain(model) if model.noises else None
        self.h, self.jac_h, self.h_and_jac, self._point_h = {}, {}, {}, {}
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

    def h_at_points(self, name: str, points) -> ca.Function:
        """``<model>_h_<name>_at_sigma``(t, x, L, u, p, q) -> Z: h at each of ``points(x, L)`` (L lower
        triangular), the columns of Z; called, not inlined, so that the host library can evaluate
        it in SIMD lanes (c_backend/lanes.py). CSE shares the terms of components the points
        leave unchanged, as in the kernel that inlined h before (the same operations, the same numbers)."""
        key = f"h_{name}_at_sigma"
        if key not in self._point_h:
            model = self.model
            h = measurement_function(model, name)
            t, x, L = model.t, ca.SX.sym("x", model.nx), ca.SX.sym("L", ca.Sparsity.lower(model.nx))
            u, p = ca.SX.sym("u", len(model.inputs)), ca.SX.sym("p", len(model.params))
            q = ca.SX.sym("q", model.measurements[name].q.shape[0])
            self._point_h[key] = ca.Function(f"{model.name}_{key}", [t, x, L, u, p, q],
                                             [ca.horzcat(*[h(t, pt, u, p, q) for pt in points(x, L)])],
                                             ["t", "x", "L", "u", "p", "q"], ["Z"], CALLED_OPTIONS)
        return self._point_h[key]

    def point_h_functions(self) -> list[ca.Function]:
        """The functions :meth:`h_at_points` made so far."""
        return list(self._point_h.values())

    def for_filter(self, family: str) -> Propagation:
        """The propagation functions of one family, per the config's ``<family>_*`` keys."""
        chosen = Discretisation.for_family(self.config, family)
        return self._propagation(chosen, chosen.suffix)

    def _propagation(self, d: Discretisation, suffix: str) -> Propagation:
        if d in self._propagations:
            return self._propagations[d]
        model, prefix = self.model, self.model.name + suffix
        options = CALLED_OPTIONS
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
            CALLED_OPTIONS)

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

"""The model-author API: named, unit-carrying symbols and the equations that use them.

A model is one file in ``models/`` that builds a :class:`Model`: it declares states, known inputs,
runtime parameters and process noises (each with a unit and a description), sets the continuous
dynamics ``dx/dt = f(t, x, u, p, w)`` and adds measurement functions ``z = h(t, x, u, p, q)``
(``q``: that measurement's own runtime parameters, e.g. a radar station's position). Everything is
CasADi ``SX``; nothing here knows about C. Errors name the state, equation or shape at fault.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import casadi as ca
import numpy as np

from . import checks
from .checks import scalar_expression
from .errors import ModelError
from .identifiers import check_measurement_name, check_model_name


@dataclass(frozen=True)
class Variable:
    """One named scalar of a model: a state, input, parameter, noise or measurement output."""

    name: str
    unit: str
    description: str

    def as_dict(self) -> dict:
        return {"name": self.name, "unit": self.unit, "description": self.description}


@dataclass
class Measurement:
    """A measurement function ``z = h(t, x, u, p, q)`` with its noise and angle handling.

    Attributes:
        outputs: one Variable per component of z.
        h: the symbolic expression (column, len(outputs)).
        params: runtime parameters of this measurement only (``q``), e.g. station coordinates.
        sigma: default 1-sigma noise per component, in the component's unit.
        wrap: per component, True where it is an angle whose innovation is wrapped to (-pi, pi].
        noise: the measurement's own noise v (:meth:`Model.measurement_noise`) when it enters h
            non-additively; ``sigma`` is then per component of v and R is the covariance of v.
        v: their symbols (column; empty when the noise is additive).
        quaternion: z is a unit quaternion (scalar-last); manifold filters take its innovation
            in their chart (a 3-vector), not as z - h.
    """

    name: str
    outputs: list[Variable]
    h: ca.SX
    params: list[Variable]
    q: ca.SX
    sigma: np.ndarray
    wrap: tuple[bool, ...]
    noise: list[Variable] = field(default_factory=list)
    v: ca.SX = field(default_factory=lambda: ca.SX(0, 1))
    quaternion: bool = False

    @property
    def size(self) -> int:
        return len(self.outputs)

    @property
    def n_innovation(self) -> int:
        """Components of the innovation: 3 for a quaternion measurement, else one per output."""
        return 3 if self.quaternion else self.size


@dataclass(frozen=True)
class QuaternionState:
    """A unit quaternion among the states, scalar-last ``[x, y, z, w]``: four consecutive states
    ``<name>_x .. <name>_w`` of x and three components of the filters' error state (a rotation vector)."""

    name: str
    description: str
    index: int          # position of <name>_x in x
    error_index: int    # position of its 3-vector in the error state

    def as_dict(self) -> dict:
        return {"name": self.name, "description": self.description, "states": list(range(self.index, self.index + 4)),
                "error_states": list(range(self.error_index, self.error_index + 3)), "convention": "scalar-last, unit norm"}


#: Suffixes of the four states of a quaternion state, scalar-last.
QUATERNION_SUFFIXES = ("x", "y", "z", "w")


@dataclass
class Model:
    """A vehicle and its sensors, written once as CasADi SX expressions.

    Build one with ``Model(name, description, paper)``, declare symbols with :meth:`state`, :meth:`input`,
    :meth:`param` and :meth:`noise`, then call :meth:`set_dynamics` and :meth:`measurement`."""

    name: str
    description: str
    paper: str = ""
    t: ca.SX = field(default_factory=lambda: ca.SX.sym("t"))
    states: list[Variable] = field(default_factory=list)
    inputs: list[Variable] = field(default_factory=list)
    params: list[Variable] = field(default_factory=list)
    noises: list[Variable] = field(default_factory=list)
    param_defaults: list[float] = field(default_factory=list)
    measurements: dict[str, Measurement] = field(default_factory=dict)
    f: ca.SX | None = None
    #: Names of the filter families codegen should generate for this model ("ekf", "ukf", ...).
    filters: tuple[str, ...] = ("ekf", "ukf")
    #: Known switching times (s) at which the dynamics jump (staging, ignition, burnout). The
    #: model's schedule is right-continuous (f at t_e is the after-event f); integrators split a
    #: step at an event so that no step straddles one (codegen/discretize.py).
    events: tuple[float, ...] = ()
    #: Codegen settings the model author wants by default (e.g. {"rk4_substeps": 2}).
    codegen_defaults: dict = field(default_factory=dict)
    #: Stand-alone model functions to export besides the filters ("f", "fd", "jac_fd", "h",
    #: "jac_h"); a model whose filters use none of them may drop some to keep the C small.
    generic_kernels: tuple[str, ...] = ("f", "fd", "jac_fd", "h", "jac_h")
    #: Named CasADi Functions a filter family asks the model for by a documented name (e.g. the
    #: gradient-descent family's earth-field reference), beside the dynamics and measurements.
    functions: dict = field(default_factory=dict)
    #: Equations (state names, measurement names) where the author allows non-differentiable
    #: operations on states (see :mod:`symkf.models.checks`).
    nondifferentiable_ok: set[str] = field(default_factory=set)
    #: Unit-quaternion states (:meth:`quaternion_state`), in declaration order.
    quaternions: list[QuaternionState] = field(default_factory=list)
    #: Families without a quaternion chart ("ekf", ...) generated anyway, on purpose: they treat each quaternion as 4 states.
    quaternion_as_vector_families: tuple[str, ...] = ()
    #: A user's model's file or module (set by ``get_model``; "" for a paper model), named by the generated files.
    source: str = ""
    #: Per state: the scale and offset of the scaled state x~ = (x - offset) / scale that scaled
    #: builds work on (:meth:`state`; codegen/scaling.py). Default 1 and 0.
    state_scale: list[float] = field(default_factory=list)
    state_offset: list[float] = field(default_factory=list)
    state_ranges: dict = field(default_factory=dict)  #: state -> (low, high, smallest 1-sigma): models/float_range.py
    #: True for the model codegen/scaling.py derives: its states are the scaled x~.
    scaled_state: bool = False
    discrete_step: tuple | None = None      #: the exact discrete step (:meth:`set_discrete_step`), if any
    #: The model file's UPPER_CASE numbers as executed: [(name, value, comment)] (the header's named constants).
    constants: list[tuple[str, float | list[float], str]] = field(default_factory=list)
    #: Parameters the filters estimate as states (models/estimation.py ``estimate``): name -> record.
    estimated: dict = field(default_factory=dict)
    _symbols: dict[str, list[ca.SX]] = field(default_factory=lambda: {k: [] for k in "xupw"})
    _pending_q: tuple | None = None
    _pending_v: tuple | None = None

    # ----------------------------------------------------------------- declarations
    def _declare(self, kind: str, table: list[Variable], name: str, unit: str, description: str) -> ca.SX:
        taken = {v.name for v in self.states + self.inputs + self.params + self.noises}
        if name in taken:
            raise ModelError(f"model '{self.name}': symbol '{name}' is declared twice")
        if not name.isidentifier():
            raise ModelError(f"model '{self.name}': symbol name '{name}' is not an identifier")
        symbol = ca.SX.sym(name)
        table.append(Variable(name, unit, description))
        self._symbols[kind].append(symbol)
        return symbol

    def state(self, name: str, unit: str, description: str, scale: float = 1.0, offset: float = 0.0) -> ca.SX:
        """Declare a state; returns its scalar symbol.

        ``scale`` and ``offset`` (in the state's unit) describe well-conditioned numbers for it: a
        scaled build (``precision="float"``, or ``scaling=True``) carries x~ = (x - offset) / scale,
        so the offset should be near the values the state takes (e.g. the Earth's radius for a
        geocentric radius) and the scale near its typical uncertainty. The scale is rounded to the
        nearest power of two and the offset to the nearest single-precision number, so that the
        transform is exact and the float C code and the double runtime agree on it bit for bit.
        """
        scale, offset = _scaling(self.name, name, scale, offset)
        symbol = self._declare("x", self.states, name, unit, description)
        self.state_scale.append(scale)
        self.state_offset.append(offset)
        return symbol

    def quaternion_state(self, name: str, description: str) -> ca.SX:
        """Declare a unit quaternion state (scalar-last ``[x, y, z, w]``, e.g. an attitude); returns
        its 4x1 symbol. It occupies four states ``<name>_x .. <name>_w`` of x; give its derivative
        in :meth:`set_dynamics` as one 4-vector under ``name``. Manifold filters (families "mekf",
        "mukf") keep it on the unit sphere and carry a 3-dim error (a rotation vector) for it."""
        if not isinstance(name, str) or not name.isidentifier():
            raise ModelError(f"model '{self.name}': quaternion state name {name!r} is not an identifier")
        if any(v.name == name for v in self.states) or any(qs.name == name for qs in self.quaternions):
            raise ModelError(f"model '{self.name}': symbol '{name}' is declared twice")
        index = self.nx
        error_index = index - len(self.quaternions)
        components = [self.state(f"{name}_{c}", "-", f"{description} ({c} component, scalar-last unit quaternion)")
                      for c in QUATERNION_SUFFIXES]
        self.quaternions.append(QuaternionState(name, description, index, error_index))
        return ca.vertcat(*components)

    def input(self, name: str, unit: str, description: str) -> ca.SX:
        """Declare a known input u (a control, or a sensor used as an input)."""
        return self._declare("u", self.inputs, name, unit, description)

    def param(self, name: str, unit: str, description: str, default: float) -> ca.SX:
        """Declare a runtime parameter p with its default value (changeable without a rebuild)."""
        self.param_defaults.append(float(default))
        return self._declare("p", self.params, name, unit, description)

    def noise(self, name: str, unit: str, description: str) -> ca.SX:
        """Declare a non-additive process noise w entering the dynamics."""
        return self._declare("w", self.noises, name, unit, description)

    # ----------------------------------------------------------------- vectors
    @property
    def x(self) -> ca.SX:
        return ca.vertcat(*self._symbols["x"]) if self.states else ca.SX(0, 1)

    @property
    def u(self) -> ca.SX:
        return ca.vertcat(*self._symbols["u"]) if self.inputs else ca.SX(0, 1)

    @property
    def p(self) -> ca.SX:
        return ca.vertcat(*self._symbols["p"]) if self.params else ca.SX(0, 1)

    @property
    def w(self) -> ca.SX:
        return ca.vertcat(*self._symbols["w"]) if self.noises else ca.SX(0, 1)

    @property
    def nx(self) -> int:
        return len(self.states)

    @property
    def n_error(self) -> int:
        """Dimension of the filters' error state: nx minus one per quaternion state."""
        return self.nx - len(self.quaternions)

    def state_names(self) -> list[str]:
        return [v.name for v in self.states]

    # ----------------------------------------------------------------- equations
    def set_dynamics(self, derivatives: dict[str, ca.SX], allow_nondifferentiable=()) -> None:
        """Set dx/dt, one expression per state name (every state exactly once).

        ``allow_nondifferentiable``: state names (or True for all) whose equation may apply floor,
        sign, fabs, if_else... to states on purpose (otherwise :meth:`validate` refuses it).
        """
        if not isinstance(derivatives, dict):
            raise ModelError(f"model '{self.name}': set_dynamics() takes a dict {{state name: d/dt expression}}, "
                             f"not a {type(derivatives).__name__}")
        derivatives = _expand_quaternions(self, derivatives)
        names = self.state_names()
        if not names:
            checks.check_sizes(self)                    # no state: the one-line refusal of validate()
        missing = [n for n in names if n not in derivatives]
        extra = [n for n in derivatives if n not in names]
        if missing or extra:
            raise ModelError(
                f"model '{self.name}': dynamics must give d/dt of every state exactly once; "
                f"missing {missing}, not states {extra}")
        rows = [scalar_expression(self.name, f"d{name}/dt", derivatives[name]) for name in names]
        self.f = ca.vertcat(*rows)
        allowed = names if allow_nondifferentiable is True else list(allow_nondifferentiable or ())
        unknown = [n for n in allowed if n not in names]
        if unknown:
            raise ModelError(f"model '{self.name}': allow_nondifferentiable names {unknown}, which are not states")
        self.nondifferentiable_ok |= set(allowed)
        self._check_free_symbols("dynamics", self.f, extra_allowed=[])

    def set_discrete_step(self, next_states: dict[str, ca.SX], dt: ca.SX) -> None:
        """Declare the model's exact discrete step x_{k+1} = φ(t, x_k, u, p, w, dt), one expression per
        state name (a quaternion as one 4-vector), for inputs u and noises w held constant over the
        step of length ``dt`` (a symbol the caller made). Filters then use φ instead of integrating
        f (codegen config ``manifold_step``); held noise has discrete covariance Q/dt
        (``manifold_noise = "held"``). f stays the model's continuous dynamics (truth, checks)."""
        if self.f is None:
            raise ModelError(f"model '{self.name}': call set_dynamics() before set_discrete_step()")
        if not isinstance(dt, ca.SX) or not dt.is_symbolic() or dt.numel() != 1:
            raise ModelError(f"model '{self.name}': set_discrete_step() needs dt as a scalar SX symbol")
        next_states = _expand_quaternions(self, dict(next_states))
        names = self.state_names()
        missing, extra = [n for n in names if n not in next_states], [n for n in next_states if n not in names]
        if missing or extra:
            raise ModelError(f"model '{self.name}': the discrete step must give every state exactly once; "
                             f"missing {missing}, not states {extra}")
        step = ca.vertcat(*[scalar_expression(self.name, f"{n}_next", next_states[n]) for n in names])
        self._check_free_symbols("discrete step", step, extra_allowed=[dt])
        self.discrete_step = (dt, step)

    def measurement_noise(self, measurement: str, noises: Sequence[tuple[str, str, str]]) -> list[ca.SX]:
        """Declare the noise v of one measurement that enters h non-additively (before calling
        :meth:`measurement`); R is then the covariance of v and ``sigma`` its 1σ per component."""
        symbols = [ca.SX.sym(f"{measurement}_{n}") for n, _, _ in noises]
        self._pending_v = (measurement, [Variable(*spec) for spec in noises], symbols)
        return symbols

    def measurement_params(self, measurement: str, params: Sequence[tuple[str, str, str]]) -> list[ca.SX]:
        """Declare the runtime parameters of one measurement (before calling :meth:`measurement`)."""
        symbols = [ca.SX.sym(f"{measurement}_{n}") for n, _, _ in params]
        self._pending_q = (measurement, [Variable(*spec) for spec in params], symbols)
        return symbols

    def measurement(self, name: str, outputs: Sequence[tuple[str, str, str, ca.SX]],
                    sigma: Sequence[float], wrap: Sequence[bool] | None = None,
                    allow_nondifferentiable: bool = False, quaternion: bool = False) -> None:
        """Add a measurement ``z = h(...)``: (name, unit, description, expression) per component.

        ``sigma``: the default 1-sigma noise per component (> 0; per component of the measurement's
        noise v if :meth:`measurement_noise` declared one, per error component (3) of a quaternion
        measurement otherwise); ``wrap``: angle components; ``quaternion``: z is a unit quaternion
        (4 outputs, scalar-last); ``allow_nondifferentiable``: h may apply floor, sign, fabs,
        if_else... to states on purpose.
        """
        check_measurement_name(self.name, name)
        if name in self.measurements:
            raise ModelError(f"model '{self.name}': measurement '{name}' is declared twice")
        pending = self._pending_q
        q_vars, q_syms = ([], [])
        if pending is not None and pending[0] == name:
            q_vars, q_syms = pending[1], pending[2]
            self._pending_q = None
        v_vars, v_syms = ([], [])
        if self._pending_v is not None and self._pending_v[0] == name:
            v_vars, v_syms = self._pending_v[1], self._pending_v[2]
            self._pending_v = None
        variables = [Variable(n, unit, desc) for n, unit, desc, _ in outputs]
        h = ca.vertcat(*[scalar_expression(self.name, f"measurement '{name}' component '{n}'", expr)
                         for n, _, _, expr in outputs])
        try:
            sigma = np.asarray(sigma, dtype=float).ravel()
        except (TypeError, ValueError):
            raise ModelError(f"model '{self.name}': measurement '{name}': sigma must be numbers") from None
        bad = [(v.name, s) for v, s in zip(variables, sigma) if not (np.isfinite(s) and s > 0)]
        if bad:
            raise ModelError(f"model '{self.name}': measurement '{name}' component '{bad[0][0]}': sigma "
                             f"{bad[0][1]} must be finite and > 0")
        wrap = tuple(bool(b) for b in (wrap if wrap is not None else [False] * len(variables)))
        if quaternion and len(variables) != 4:
            raise ModelError(f"measurement '{name}': a quaternion measurement has 4 outputs, got {len(variables)}")
        n_sigma = len(v_vars) or (3 if quaternion else len(variables))
        if sigma.size != n_sigma or len(wrap) != len(variables):
            raise ModelError(f"measurement '{name}': {len(variables)} outputs ({n_sigma} noise components) but "
                             f"{sigma.size} sigmas and {len(wrap)} wrap flags")
        q = ca.vertcat(*q_syms) if q_syms else ca.SX(0, 1)
        v = ca.vertcat(*v_syms) if v_syms else ca.SX(0, 1)
        self._check_free_symbols(f"measurement '{name}'", h, extra_allowed=q_syms + v_syms)
        self.measurements[name] = Measurement(name, variables, h, q_vars, q, sigma, wrap, v_vars, v, bool(quaternion))
        if allow_nondifferentiable:
            self.nondifferentiable_ok.add(name)

    def _check_free_symbols(self, what: str, expr: ca.SX, extra_allowed: list[ca.SX]) -> None:
        known = {s.name() for kind in self._symbols.values() for s in kind}
        known |= {self.t.name()} | {s.name() for s in extra_allowed}
        unknown = sorted({s.name() for s in ca.symvar(expr)} - known)
        if unknown:
            raise ModelError(f"model '{self.name}': {what} uses undeclared symbols {unknown}; "
                             f"declare them with state()/input()/param()/noise()")

    # ----------------------------------------------------------------- checks
    def validate(self) -> "Model":
        """Raise ModelError if the model is incomplete; return self for chaining."""
        check_model_name(self.name)
        if self.f is None:
            raise ModelError(f"model '{self.name}': set_dynamics() was never called")
        checks.check_sizes(self)
        events = np.asarray(self.events, dtype=float)
        if not np.all(np.isfinite(events)) or np.any(np.diff(events) <= 0):
            raise ModelError(f"model '{self.name}': events must be finite and strictly increasing, got {self.events}")
        checks.check_equations(self)
        checks.check_unused(self)
        return self

    def describe(self) -> dict:
        """A JSON-ready description of every symbol (for manifests and documentation)."""
        return {
            "name": self.name,
            "description": self.description,
            "paper": self.paper,
            "states": [v.as_dict() for v in self.states],
            "inputs": [v.as_dict() for v in self.inputs],
            "params": [dict(v.as_dict(), default=d) for v, d in zip(self.params, self.param_defaults)],
            "noises": [v.as_dict() for v in self.noises],
            "events": [float(e) for e in self.events],
            "measurements": {m.name: _describe_measurement(m) for m in self.measurements.values()},
            **({"quaternions": [qs.as_dict() for qs in self.quaternions], "error_state_dim": self.n_error}
               if self.quaternions else {}),
            **({"state_scaling": {"scale": list(self.state_scale), "offset": list(self.state_offset),
                                  "kernels_use_scaled_state": self.scaled_state}} if self.has_scaling else {}),
            **({"constants": [{"name": n, "value": v, "comment": c} for n, v, c in self.constants]}
               if self.constants else {}),
            **({"source": self.source} if self.source else {}),
            **({"estimated_parameters": list(self.estimated.values())} if self.estimated else {}),
        }

    @property
    def has_scaling(self) -> bool:
        """True if any state declares a scale or an offset other than 1 and 0."""
        return any(s != 1.0 for s in self.state_scale) or any(o != 0.0 for o in self.state_offset)


def _expand_quaternions(model: "Model", derivatives: dict) -> dict:
    """{quaternion name: 4-vector} -> one entry per component state."""
    expanded = dict(derivatives)
    for qs in model.quaternions:
        if qs.name not in expanded:
            continue
        value = expanded.pop(qs.name)
        value = ca.SX(value) if not isinstance(value, ca.SX) else value
        if value.shape != (4, 1):
            raise ModelError(f"model '{model.name}': d{qs.name}/dt must be a 4-vector (scalar-last), "
                             f"got shape {value.shape}")
        expanded.update({f"{qs.name}_{c}": value[i] for i, c in enumerate(QUATERNION_SUFFIXES)})
    return expanded


def _describe_measurement(m: Measurement) -> dict:
    return {"outputs": [v.as_dict() for v in m.outputs], "params": [v.as_dict() for v in m.params],
            "sigma": m.sigma.tolist(), "wrap": list(m.wrap),
            **({"noise": [v.as_dict() for v in m.noise]} if m.noise else {}),
            **({"quaternion": True} if m.quaternion else {})}


def _scaling(model: str, name: str, scale, offset) -> tuple[float, float]:
    """A state's (scale, offset): scale a power of two > 0, offset a single-precision number."""
    try:
        scale, offset = float(scale), float(offset)
    except (TypeError, ValueError):
        raise ModelError(f"model '{model}': state '{name}': scale and offset must be numbers") from None
    if not (np.isfinite(scale) and scale > 0) or not np.isfinite(offset):
        raise ModelError(f"model '{model}': state '{name}': scale must be finite and > 0 and offset finite, "
                         f"got scale={scale}, offset={offset}")
    scale = float(2.0 ** np.round(np.log2(scale)))
    if abs(offset) > 3.0e38 or not 1e-30 < scale < 1e30:
        raise ModelError(f"model '{model}': state '{name}': scale {scale} or offset {offset} is outside the "
                         "range of single precision")
    return scale, float(np.float32(offset))

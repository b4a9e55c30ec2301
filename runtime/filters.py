"""One filter object for every generated filter, built from the manifest's filter spec.

A :class:`Filter` reads its :class:`~symkf.codegen.spec.FilterSpec` (which kernel predicts,
updates and steps with each measurement, which outputs are the carried state and which are
diagnostics, default scalars), makes one numpy buffer per argument of those kernels (shared
arguments once, per-measurement arguments once per measurement), binds every kernel to them once,
and exposes ``x``, ``P`` and the diagnostics ``y``/``S`` as read-only views, FilterPy-style.
``predict``, ``update`` and ``step`` are one kernel call each; ``run`` is the whole loop in C
(or, on the CasADi-VM backend, the same kernel called step by step).

Every call enforces :mod:`symkf.runtime.contract` before it writes a buffer; the kernels write
x and P only on success, so when anything raises, x, P and t are bit-identical to before.

Where a step kernel has a trusted partner (the kernel its C run loop iterates once a step has
succeeded, ``Kernel.trusted``: an MEKF's step without the checks of |q| = 1, P PSD and R diagonal
and without y, S), the fast path of :meth:`Filter.step` calls that partner while x and P are the
filter's own (a step succeeded and nothing was written from Python since): the same x, P and codes.
It keeps the step's inputs (a :class:`Replay`), and :meth:`Filter.y` / :meth:`Filter.S` compute
the diagnostics from them when asked, with the checked step kernel: bit-identical to a checked
step's. Every write from Python first does that replay and makes the next step a checked one.
Paper-specific filters (attitude, MARG) are thin subclasses that name their arguments.
"""
from __future__ import annotations

from copy import deepcopy
from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2

from symkf.codegen.spec import STATUS_GATED, STATUS_NONFINITE, FilterSpec
from . import contract
from . import fastcall
from .backends import SymkfError
from .contract import as_array, covariance, read_only  # noqa: F401  (re-exported for older imports)

#: Inputs that change every step of a run (the rest are constants of the filter).
PER_CALL = ("t", "dt", "u", "q", "z", "mask", "acc", "mag")


def _buffer(shape: tuple[int, int], dtype=np.float64) -> np.ndarray:
    """A zeroed column-major buffer: (r,) for a column vector, (r, c) for a matrix."""
    return np.zeros(shape[0], dtype) if shape[1] == 1 else np.zeros(shape, dtype, order="F")


class StateScaling:
    """x = offset + scale x~, P = S P~ S (S = diag(scale)): the conversion between the physical
    state a user gives and reads and the scaled state the kernels of a scaled build carry
    (codegen/scaling.py). Done in double; scales are powers of two, so it is exact."""

    def __init__(self, description: dict):
        info = description["state_scaling"]
        self.scale, self.offset = np.array(info["scale"]), np.array(info["offset"])
        self.outer = np.outer(self.scale, self.scale)
        #: Q is n x n in state units (additive noise) unless the model declares noises w.
        self.scales_Q = not description.get("noises")

    @staticmethod
    def of(description: dict) -> "StateScaling | None":
        info = description.get("state_scaling")
        return StateScaling(description) if info and info["kernels_use_scaled_state"] else None

    def x_to_kernel(self, x: np.ndarray) -> np.ndarray:
        return (x - self.offset) / self.scale

    def x_from_kernel(self, x: np.ndarray) -> np.ndarray:
        return self.offset + self.scale * np.asarray(x, dtype=float)

    def P_to_kernel(self, P: np.ndarray) -> np.ndarray:
        return P / self.outer

    def P_from_kernel(self, P: np.ndarray) -> np.ndarray:
        return np.asarray(P, dtype=float) * self.outer


@dataclass
class Replay:
    """What a trusted step (module docstring) of one measurement needs and leaves: the trusted
    kernel's name, that step's carried state and per-step inputs, kept by the C fast path, and
    whether its y, S are still to be computed from them (``stale[0]`` = 1, set in C)."""

    kernel: str
    buffers: dict[str, np.ndarray]
    stale: np.ndarray


@dataclass
class RunResult:
    """A whole run: the state (and covariance) after every step and each step's status code."""

    x: np.ndarray                  # (N, n)
    P: np.ndarray | None           # (N, n, n), None for a filter without covariance
    status: np.ndarray             # (N,) int: 0, SYMKF_GATED or a SYMKF_ERR_* code

    @property
    def failed_steps(self) -> np.ndarray:
        """Steps that failed (state kept); gated steps are not failures."""
        return np.flatnonzero((self.status != 0) & (self.status != STATUS_GATED))

    @property
    def gated_steps(self) -> int:
        """Number of steps whose update the chi-square gate refused."""
        return int(np.count_nonzero(self.status == STATUS_GATED))

    @property
    def q(self) -> np.ndarray:
        """The attitude quaternions (first four states) of an attitude or MARG filter."""
        return self.x[:, 0:4]


class Filter:
    """A generated filter (EKF, UKF, continuous-discrete EKF, ...) of one compiled model.

    Args:
        compiled: a :class:`~symkf.runtime.CompiledModel`.
        spec: the filter's name in the manifest (``compiled.filters``) or its FilterSpec.
        x0, P0: initial state and covariance (P0 symmetric positive semi-definite).
        Q: process-noise power spectral density, symmetric PSD: n x n, additive (discrete noise
            Q dt), or, for a model that declares noise(), nw x nw of its noises w (discrete noise
            G Q G^T dt, G = df/dw at the step start; see codegen/families/kalman.py).
        R: {measurement: covariance} (symmetric PD); default diag(sigma^2) from the model.
        p: runtime parameters (default: the model's defaults).
        gate: {measurement: probability in (0, 1) or {"threshold": value}} chi-square gates.
        **scalars: scalar inputs of the kernels, e.g. ``kappa`` (defaults from the spec).

    ``step(t, dt, z, q=...)`` with float64 arrays of the right shape takes a fast path: the
    contract's checks, the copies and the kernel call in one C call (:mod:`symkf.runtime.fastcall`);
    any other call, and every error, takes the Python path below, with the same rules.
    """

    #: The array arguments of :meth:`step` in the order its fast path takes them.
    FAST_ARGUMENTS = ("z", "q", "mask", "u")
    #: What the fast path writes for an omitted (None) array: a mask is all ones, an input ``u``
    #: keeps its held value; any other argument with values is required (the Python path says so).
    FAST_NONE = {"mask": "ones", "u": "keep"}
    #: How the fast path checks an array: a mask is exactly 0 or 1; z must be finite where the
    #: mask uses it (the kernel never reads a masked component; the Python path accepts a NaN
    #: there too); anything else finite.
    FAST_CHECK = {"mask": "mask", "z": "used"}

    def __init__(self, compiled, spec, x0, P0=None, Q=None, R: dict | None = None, p=None,
                 gate: dict | None = None, **scalars):
        self.spec: FilterSpec = compiled.filters[spec] if isinstance(spec, str) else spec
        self.family = self.spec.name
        self.model = compiled.model
        self._backend = compiled.backend
        self._clock = np.zeros(1)           # the filter's time t (the fast path of step sets it in C)
        self.kernels = {name: self._backend.kernels[name] for name in self.spec.kernel_names()}
        self._dtype = getattr(self._backend, "dtype", np.dtype(np.float64))
        self._scaling = StateScaling.of(self.model)
        self._make_buffers()
        self.n = self._buffers["x"].size
        self._views = {name: read_only(self._buffers[name]) for name in ("x", "P") if name in self._buffers}
        self._set_initial(x0, P0, Q, p, scalars)
        self._set_noise(R)
        for name, value in contract.known_keys("gate", gate, self.spec.measurements).items():
            self.set_gate(name, **(value if isinstance(value, dict) else {"probability": value}))
        self.t = 0.0
        self._default = self.spec.measurements[0]
        self._bind()

    # ------------------------------------------------------------------ copies
    #: What a copy shares with its original: the compiled model and what describes it (read only).
    _SHARED = frozenset({"spec", "family", "model", "_backend", "kernels", "_dtype", "_scaling"})
    #: What a copy binds afresh: calls into the C library hold pointers to the original's buffers.
    _BOUND = frozenset({"step", "_calls", "_fast", "_fast_default", "_fast_sample", "_views", "_replay_calls",
                        "_trusted_calls", "_diagnostic_views"})

    def copy(self) -> "Filter":
        """An independent filter at this filter's state (x, P, t, noises, gates, options): stepping
        either leaves the other as it was. ``copy.copy`` and ``copy.deepcopy`` give the same."""
        clone = object.__new__(type(self))
        clone.__dict__.update({key: value if key in self._SHARED else deepcopy(value)
                               for key, value in self.__dict__.items() if key not in self._BOUND})
        clone._views = {name: read_only(clone._buffers[name]) for name in self._views}
        clone._bind()
        return clone

    def __copy__(self) -> "Filter":
        return self.copy()

    def __deepcopy__(self, memo) -> "Filter":
        return self.copy()

    def __reduce__(self):
        raise TypeError(f"a {type(self).__name__} holds pointers into its compiled library and cannot be "
                        "pickled; send the model and the state instead (model name or file, x, P, t) and "
                        "make the filter again where it is needed")

    # ------------------------------------------------------------------ buffers
    def _make_buffers(self) -> None:
        """One buffer per argument name; per-measurement ones once per measurement."""
        self._buffers: dict[str, np.ndarray] = {}
        self.measurements: dict[str, dict[str, np.ndarray]] = {m: {} for m in self.spec.measurements}
        per_measurement = set(self.spec.measurement_inputs) | set(self.spec.diagnostics)
        for kernel, measurement in self._kernel_roles():
            info = self.kernels[kernel]
            for name, shape in info.inputs + info.outputs[:-1]:
                if measurement is not None and name in per_measurement:
                    self.measurements[measurement].setdefault(name, _buffer(shape, self._dtype))
                else:
                    self._buffers.setdefault(name, _buffer(shape, self._dtype))
        for buffers in self.measurements.values():
            if "mask" in buffers:
                buffers["mask"][:] = 1.0
        self._make_replays()

    def _make_replays(self) -> None:
        """A :class:`Replay` per measurement whose step kernel has a trusted partner, and the flag
        the fast path sets once a step has succeeded (``_own_state``; 0 after any write from Python)."""
        self._own_state = np.zeros(1)
        self._replays: dict[str, Replay] = {}
        for name, kernel in self.spec.step.items():
            trusted = self._trusted_kernel(name)
            if trusted:
                live = self._measurement_buffers(name)
                kept = [n for n in self.spec.state + self.kernels[kernel].per_step if live[n].size]
                self._replays[name] = Replay(trusted, {n: live[n].copy(order="K") for n in kept}, np.zeros(1))

    def _trusted_kernel(self, name: str) -> str:
        """The trusted partner of the run kernel of measurement ``name`` if it takes the step
        kernel's inputs and writes some of its outputs (x, P, status), else ""."""
        kernels, step = self._backend.kernels, self.kernels[self.spec.step[name]]
        run = kernels.get(self.spec.run.get(name, ""))
        trusted = kernels.get(run.trusted) if run is not None and run.trusted else None
        fits = trusted is not None and trusted.inputs == step.inputs and set(trusted.outputs) <= set(step.outputs)
        return trusted.name if fits else ""

    def _measurement_buffers(self, name: str) -> dict[str, np.ndarray]:
        """Every buffer a kernel of measurement ``name`` reads or writes, by argument name."""
        return {**self._buffers, **self.measurements[name]}

    def _kernel_roles(self) -> list[tuple[str, str | None]]:
        # a prediction that reads a measurement input (the augmented UKF's R) reads the first one's
        roles = [(self.spec.predict, self.spec.measurements[0])] if self.spec.predict else []
        roles += [(k, m) for m, k in self.spec.update.items()]
        return roles + [(k, m) for m, k in self.spec.step.items()]

    def _set_initial(self, x0, P0, Q, p, scalars: dict) -> None:
        self.x = x0
        if "P" in self._buffers:
            self.P = P0
        if "Q" in self._buffers:
            self.Q = Q
        if "p" in self._buffers:
            self.p = [v["default"] for v in self.model["params"]] if p is None else p
        known = {name: value for name, value in self.spec.defaults.items()}
        known.update(contract.known_keys("options", scalars, self.spec.defaults))
        for name, value in known.items():
            self._buffers[name][0] = self._fits(name, contract.real(name, value))

    def _set_noise(self, R: dict | None) -> None:
        R = contract.known_keys("R", R, self.spec.measurements)
        for name in self.spec.measurements:
            if "R" in self.measurements[name]:
                self.set_R(name, R[name] if name in R else self._default_R(name))

    def _default_R(self, name: str) -> np.ndarray:
        return np.diag(np.square(self.model["measurements"][name]["sigma"]))

    def _bind(self) -> None:
        self._calls = {}
        for kernel, measurement in self._kernel_roles():
            buffers = self._buffers if measurement is None else self._measurement_buffers(measurement)
            self._calls[kernel] = self._backend.bind(kernel, buffers)
        self._trusted_calls, self._replay_calls, self._diagnostic_views = {}, {}, {}
        for name, replay in self._replays.items():
            live = self._measurement_buffers(name)
            # its inputs are tested by the fast path (arguments), by the setters (constants) and on
            # output (x, P): the entry without the inputs' finiteness test (0.6k instructions for the MEKF)
            self._trusted_calls[name] = self._backend.bind(replay.kernel, live, entry="unchecked_v")
            self._replay_calls[name] = self._backend.bind(self.spec.step[name], {**live, **replay.buffers})
        self._make_fast_paths()

    def _make_fast_paths(self) -> None:
        """The C fast path of :meth:`step` per measurement (None without the extension), and
        ``self.step`` taking plain calls in C."""
        self._fast = {name: self._fast_step(name, self.FAST_ARGUMENTS) for name in self.spec.step}
        self._fast_default = self._fast.get(self._default)
        self._install_step(Filter.step, self._fast_default, ("t", "dt") + self.FAST_ARGUMENTS,
                           steps=self._fast, select="measurement")

    def _install_step(self, function, default, arguments: tuple, **options) -> None:
        """Set ``self.step`` to a C :func:`~symkf.runtime.fastcall.method` over ``function``: a plain
        call then runs no Python frame (issue 12: that frame was ~1,000 of the ~2,200 instructions a
        call cost beyond the kernel); any other call runs ``function``. Only where ``function`` is
        this object's ``step`` (a subclass's own ``step`` is left alone)."""
        self.__dict__.pop("step", None)
        if type(self).step is function:
            fast = fastcall.method(function, self, default, arguments, **options)
            if fast is not None:
                self.step = fast

    @property
    def t(self) -> float:
        """The filter's time: the end of its last step (or as set)."""
        return float(self._clock[0])

    @t.setter
    def t(self, value) -> None:
        self._clock[0] = contract.real("t", value)

    @property
    def fast_calls(self) -> int:
        """How many calls of ``step`` took the C fast path (since it was last switched on)."""
        steps = list(self._fast.values()) + [getattr(self, "_fast_sample", None)]
        return sum(step.calls for step in steps if step is not None)

    @property
    def fast_path(self) -> bool:
        """Whether plain ``step`` calls take the C fast path. Set False to send every call through
        the Python contract (same results; for comparisons), True to restore it."""
        return self._fast_default is not None or getattr(self, "_fast_sample", None) is not None

    @fast_path.setter
    def fast_path(self, on: bool) -> None:
        if on:
            self._make_fast_paths()
        else:
            self._fast, self._fast_default, self._fast_sample = {}, None, None
            self.__dict__.pop("step", None)

    def _fast_step(self, name: str, keys: tuple[str, ...]):
        """The fast path of ``step`` with measurement ``name`` (None without the C extension)."""
        buffers = self.measurements[name]
        slots = []
        for key in keys:
            buffer = buffers.get(key, self._buffers.get(key) if key == "u" else None)
            if buffer is None:
                slots.append((None, "absent", "finite"))
            else:
                required = "decline" if buffer.size else "keep"
                slots.append((buffer, self.FAST_NONE.get(key, required), self.FAST_CHECK.get(key, "finite")))
        trusted = None
        if name in self._replays:
            replay, live = self._replays[name], self._measurement_buffers(name)
            trusted = (self._trusted_calls[name], self._own_state, replay.stale,
                       [(live[n], kept, n in self.spec.state) for n, kept in replay.buffers.items()])
        return fastcall.step(self._calls[self.spec.step[name]], self._buffers.get("t"), self._buffers.get("dt"),
                             self._clock, slots, (self._buffers, buffers), trusted)

    def kernel_buffer(self, name: str, measurement: str | None = None) -> np.ndarray:
        """The writable buffer a bound kernel reads (no checks: for benchmarks that restore the
        state between timed kernel calls)."""
        self._before_write()
        return self._buffers[name] if name in self._buffers else self._measurement(measurement)[name]

    def kernel_call(self, kind: str, measurement: str | None = None):
        """The bound compiled call behind ``predict``/``update``/``step`` (no argument checks):
        for benchmarks that time the C call alone. Returns a callable giving the status code."""
        if kind == "predict":
            return self._calls[self.spec.predict]
        return self._calls[getattr(self.spec, kind)[measurement or self._default]]

    # ------------------------------------------------------------------ state and settings
    @property
    def x(self) -> np.ndarray:
        """The state estimate (a read-only view of the buffer the C code writes; a read-only
        physical copy for a scaled build)."""
        if self._scaling is None:
            return self._views["x"]
        return read_only(self._scaling.x_from_kernel(self._buffers["x"]))

    @x.setter
    def x(self, value) -> None:
        x = contract.finite_array("x", value, self._buffers["x"].shape)
        x = contract.unit_quaternions("x", x, self.model.get("quaternions", []))
        self._write_state("x", x if self._scaling is None else self._scaling.x_to_kernel(x))

    @property
    def P(self) -> np.ndarray:
        """The covariance (read-only view, or physical copy for a scaled build); set it with a
        symmetric PSD matrix."""
        if self._scaling is None:
            return self._views["P"]
        return read_only(self._scaling.P_from_kernel(self._buffers["P"]))

    @P.setter
    def P(self, value) -> None:
        P = covariance("P", value, self._buffers["P"].shape[0])
        self._write_state("P", P if self._scaling is None else self._scaling.P_to_kernel(P))

    @property
    def Q(self) -> np.ndarray:
        Q = self._buffers["Q"]
        return read_only(Q if not self._scales_Q else self._scaling.P_from_kernel(Q))

    @Q.setter
    def Q(self, value) -> None:
        Q = covariance("Q", value, self._buffers["Q"].shape[0])
        self._write_state("Q", Q if not self._scales_Q else self._scaling.P_to_kernel(Q))

    @property
    def _scales_Q(self) -> bool:
        return self._scaling is not None and self._scaling.scales_Q

    def _write_state(self, name: str, value: np.ndarray) -> None:
        """Write a checked value; for a float build refuse one that float cannot hold (buffer unchanged)."""
        value = self._fits(name, value, " after scaling" if self._scaling is not None else "")
        self._before_write()
        self._buffers[name][:] = value

    def _before_write(self) -> None:
        """Before anything is written from Python: the diagnostics trusted steps left (they read
        those steps' inputs and the constants about to change), and the next fast step is a
        checked one (the trusted kernel relies on a state only steps wrote)."""
        for name in self._replays:
            self._replay(name)
        self._own_state[0] = 0.0

    def _replay(self, name: str) -> None:
        """y, S of the last step with measurement ``name`` if a trusted step left them: the checked
        step kernel on the inputs it kept (the same expressions: a checked step's y, S bit for bit;
        its x, P land in the replay's buffers). NaN if that kernel refuses what the trusted one
        took: a P off the PSD test after a successful step (none seen; codegen/families/mekf.py
        ``mekf_run_kernels``)."""
        replay = self._replays.get(name)
        if replay is None or not replay.stale[0]:
            return
        replay.stale[0] = 0.0
        if self._replay_calls[name]() not in (0, STATUS_GATED):
            for key in self.spec.diagnostics:
                self.measurements[name][key][...] = np.nan

    def _fits(self, name: str, value, where: str = ""):
        """``value`` unchanged if the buffers' element type holds it; for a float build, ValueError
        (nothing written, no NumPy overflow warning) if a finite value overflows float (|value| >
        3.4e38), checked before any buffer of the call is written. NaN and Inf pass: the contract
        and the kernels decide about them."""
        if self._dtype == np.float64:
            return value
        array = np.asarray(value, dtype=float)
        with np.errstate(over="ignore"):
            converted = array.astype(self._dtype)
        if np.any(np.isinf(converted) & np.isfinite(array)):
            raise ValueError(f"{name}: a value overflows {self._dtype.name} (|value| > "
                             f"{np.finfo(self._dtype).max:.3g}{where}), the range of this float build")
        return value

    @property
    def p(self) -> np.ndarray:
        return read_only(self._buffers["p"])

    @p.setter
    def p(self, value) -> None:
        value = self._fits("p", contract.finite_array("p", value, self._buffers["p"].shape))
        self._before_write()
        self._buffers["p"][:] = value

    def R(self, measurement: str | None = None) -> np.ndarray:
        return read_only(self._measurement(measurement)["R"])

    def set_R(self, measurement: str, value) -> None:
        """Measurement noise covariance (symmetric positive definite)."""
        buffers = self._measurement(measurement)
        name = f"R[{measurement}]"
        value = self._fits(name, covariance(name, value, buffers["R"].shape[0], definite=True))
        self._before_write()
        buffers["R"][:] = value

    def set_gate(self, measurement: str, probability: float | None = None, threshold: float | None = None) -> None:
        """Chi-square innovation gate: an update whose y^T S^-1 y exceeds the ``probability``
        quantile of chi2(k) (k = used components), or ``threshold``, is skipped (state unchanged,
        status SYMKF_GATED). Neither given: no gate (the default)."""
        buffers = self._measurement(measurement)
        if "gate" not in buffers:
            raise ValueError(f"gate: filter '{self.family}' has no innovation gate")
        gate = np.zeros_like(buffers["gate"])
        if probability is not None and threshold is not None:
            raise ValueError("gate: give a probability or a threshold, not both")
        if probability is not None:
            probability = contract.real("probability", probability)
            if not 0 < probability < 1:
                raise ValueError(f"probability: must be in (0, 1), got {probability}")
            gate = chi2.ppf(probability, np.arange(1, gate.size + 1))
        elif threshold is not None:
            threshold = contract.real("threshold", threshold)
            if threshold <= 0:
                raise ValueError(f"threshold: must be > 0, got {threshold}")
            gate[:] = threshold
        self._before_write()
        buffers["gate"][:] = gate

    def y(self, measurement: str | None = None) -> np.ndarray:
        """Innovation of the last update with ``measurement``."""
        return self._diagnostic("y", measurement)

    def S(self, measurement: str | None = None) -> np.ndarray:
        """Innovation covariance of the last update with ``measurement``."""
        return self._diagnostic("S", measurement)

    def _diagnostic(self, key: str, measurement: str | None) -> np.ndarray:
        """The read-only view of diagnostic ``key`` (made once), replayed first if a trusted step left it."""
        name = self._default if measurement is None else measurement
        buffers = self._measurement(name)
        self._replay(name)
        if (name, key) not in self._diagnostic_views:
            self._diagnostic_views[name, key] = read_only(buffers[key])
        return self._diagnostic_views[name, key]

    def _measurement(self, name: str | None) -> dict[str, np.ndarray]:
        name = self._default if name is None else name
        if name not in self.measurements:
            raise ValueError(f"measurement: '{name}' is not one of {list(self.measurements)}")
        return self.measurements[name]

    # ------------------------------------------------------------------ steps
    def predict(self, t: float, dt: float, u=None) -> None:
        """Propagate from time t to t + dt."""
        if not self.spec.predict:
            raise ValueError(f"predict: filter '{self.family}' only steps (it has no separate prediction)")
        t, dt, u = contract.real("t", t), contract.time_step(dt), self._input(u)
        self._write_time(t, dt, u)
        self._check(self._calls[self.spec.predict](), "predict")
        self.t = t + dt

    def update(self, z, measurement: str | None = None, q=None, mask=None, t: float | None = None,
               u=None, nan: str = "raise") -> int:
        """Update with measurement z taken at time t (default: the filter's time).

        Args:
            q: the measurement's runtime parameters (required when it has any).
            mask: 1/0 per component; 0 ignores that component.
            nan: "raise" (a NaN/Inf component is an error) or "mask" (it is skipped).
        Returns:
            0, or SYMKF_GATED if the innovation gate refused the update (state unchanged).
        """
        name = self._measurement_name(measurement, "update")
        values = self._measurement_values(name, {"z": z, "q": q, "mask": mask}, nan)
        t = self.t if t is None else contract.real("t", t)
        u = self._input(u)
        self._write_time(t, None, u)
        self._write_measurement(name, values)
        return self._check(self._calls[self.spec.update[name]](), f"update '{name}'", name)

    def step(self, t: float, dt: float, z, measurement: str | None = None, q=None, mask=None,
             u=None, nan: str = "raise") -> int:
        """predict(t, dt) then update(z) at t + dt — one call into the compiled code. Returns 0
        or SYMKF_GATED (prediction applied, update refused by the gate)."""
        fast = self._fast_default if measurement is None else self._fast.get(measurement) if type(measurement) is str else None
        if fast is not None and nan == "raise":
            code = fast(t, dt, z, q, mask, u)     # sets self.t; None: not a plain call, the Python path decides
            if code is not None:
                return code
        name = self._measurement_name(measurement, "step")
        return self._step(name, t, dt, {"z": z, "q": q, "mask": mask}, u, nan)

    def _step(self, name: str, t, dt, given: dict, u, nan: str) -> int:
        values = self._measurement_values(name, given, nan)
        t = self.t if t is None else contract.real("t", t)
        dt, u = contract.time_step(dt), self._input(u)
        self._write_time(t, dt, u)
        self._write_measurement(name, values)
        code = self._check(self._calls[self.spec.step[name]](), f"step '{name}'", name)
        self.t = t + dt
        return code

    # ------------------------------------------------------------------ validation and writes
    def _measurement_name(self, measurement: str | None, kind: str) -> str:
        name = self._default if measurement is None else measurement
        if name not in getattr(self.spec, kind):
            raise ValueError(f"measurement: '{name}' is not one of {list(getattr(self.spec, kind))} "
                             f"(filter '{self.family}', {kind})")
        return name

    def _input(self, u) -> np.ndarray | None:
        if u is None or "u" not in self._buffers:
            if u is not None:
                raise ValueError(f"u: filter '{self.family}' has no inputs")
            return None
        return self._fits("u", contract.finite_array("u", u, self._buffers["u"].shape))

    def _measurement_values(self, name: str, given: dict, nan: str) -> dict[str, np.ndarray]:
        """Validated per-call measurement inputs (z, q, mask or a family's own); writes nothing."""
        nan = contract.nan_policy(nan) if nan != "raise" else nan
        buffers = self.measurements[name]
        values = {}
        for key, value in given.items():
            if key not in buffers:
                if value is not None:
                    raise ValueError(f"{key}: measurement '{name}' of filter '{self.family}' takes no {key}")
                continue
            if key == "mask":
                values[key] = None if value is None else contract.mask(value, buffers[key].shape)
            elif key == "q" and value is None and buffers[key].size:
                params = [v["name"] for v in self.model["measurements"][name]["params"]]
                raise ValueError(f"q: measurement '{name}' needs its parameters {params} (q=...) on every call")
            elif value is not None or buffers[key].size:
                values[key] = contract.exact_array(key, value, buffers[key].shape)
        if nan == "mask":
            values = self._mask_nonfinite(values, buffers)
        for key, value in values.items():
            if value is not None:
                self._fits(key, value)
        return values

    def _mask_nonfinite(self, values: dict, buffers: dict) -> dict:
        """nan="mask": non-finite measurement components are masked (the whole measurement when
        its mask is one number)."""
        z = values["z"]
        finite = np.isfinite(z)
        mask = np.ones(buffers["mask"].shape) if values.get("mask") is None else values["mask"]
        values["mask"] = mask * (finite if mask.shape == finite.shape else float(finite.all()))
        values["z"] = np.where(finite, z, 0.0)
        return values

    def _write_measurement(self, name: str, values: dict) -> None:
        self._before_write()
        buffers = self.measurements[name]
        for key, value in values.items():
            if key == "mask":
                buffers["mask"][...] = 1.0 if value is None else value
            else:
                buffers[key][...] = value

    def _write_time(self, t: float, dt: float | None, u) -> None:
        """Time (and input) of a call: checked for the buffers' type before anything is written;
        the measurement's values are written after this (they are already checked)."""
        self._fits("t", t)
        self._fits("dt", dt if dt is not None else 0.0)
        self._before_write()
        if "t" in self._buffers:
            self._buffers["t"][0] = t
        if dt is not None:
            self._buffers["dt"][0] = dt
        if u is not None:
            self._buffers["u"][:] = u

    def _check(self, code: int, what: str, measurement: str | None = None) -> int:
        if code == 0 or code == STATUS_GATED:
            return code
        detail = ""
        if code == STATUS_NONFINITE and measurement is not None:
            detail = self._nonfinite_detail(self.measurements[measurement])
        raise SymkfError(f"{self.family} {what}", code, detail)

    @staticmethod
    def _nonfinite_detail(buffers: dict) -> str:
        if "z" not in buffers:
            return ""
        mask = buffers.get("mask", np.ones(1))
        bad = ~np.isfinite(buffers["z"]) & (mask > 0.5 if mask.shape == buffers["z"].shape else mask[0] > 0.5)
        if not bad.any():
            return ""
        return f"measurement z has NaN/Inf at components {np.flatnonzero(bad).tolist()}; pass nan='mask' to skip them"

    # ------------------------------------------------------------------ whole runs
    def run(self, times, z, measurement: str | None = None, q=None, mask=None, u=None,
            nan: str = "raise") -> RunResult:
        """Filter a whole record in one compiled call: step k predicts from times[k-1] to times[k]
        (the first step has dt = 0) and updates with z[k]. The filter's x, P and t end at the last
        step. A step that fails keeps the state and records its code in ``status``.

        Args:
            times: (N,) strictly increasing; z: (N, m); q: (N, nq) or (nq,); mask: (N, m) or None;
            u: (N, nu) or (nu,) or None (the current input held).
        """
        name = self._measurement_name(measurement, "step")
        times = contract.run_times(times)
        n_steps = times.size
        per_step = {"t": np.concatenate([times[:1], times[:-1]]), "dt": np.diff(times, prepend=times[:1])}
        per_step.update(self._run_series(name, n_steps, {"z": z, "q": q, "mask": mask}, u, nan))
        return self._run(name, per_step, n_steps)

    def _run_series(self, name: str, n_steps: int, given: dict, u, nan: str) -> dict[str, np.ndarray]:
        """Validated per-step arrays of a run (same rules as step(), for every row at once)."""
        nan = contract.nan_policy(nan)
        buffers = self.measurements[name]
        series = {}
        for key, value in given.items():
            if key not in buffers:
                if value is not None:
                    raise ValueError(f"{key}: measurement '{name}' of filter '{self.family}' takes no {key}")
                continue
            shape = buffers[key].shape
            if key == "q" and value is None and buffers[key].size:
                params = [v["name"] for v in self.model["measurements"][name]["params"]]
                raise ValueError(f"q: measurement '{name}' needs its parameters {params} (q=...)")
            if key == "mask":
                series[key] = np.ones((n_steps,) + shape) if value is None else contract.mask(value, (n_steps,) + shape)
            elif value is None and not buffers[key].size:
                series[key] = np.zeros((n_steps,) + shape)
            else:
                series[key] = self._series(key, value, n_steps, shape)
        if "u" in self._buffers:
            series["u"] = self._series("u", self._buffers["u"] if u is None else u, n_steps, self._buffers["u"].shape)
            if not np.isfinite(series["u"]).all():
                raise ValueError("u: contains NaN or Inf")
        elif u is not None:
            raise ValueError(f"u: filter '{self.family}' has no inputs")
        return self._run_nan_policy(series, buffers, nan)

    @staticmethod
    def _series(key: str, value, n_steps: int, shape: tuple) -> np.ndarray:
        if np.shape(value) == shape:                          # one value held for every step
            return np.broadcast_to(as_array(key, value, shape), (n_steps,) + shape)
        return as_array(key, value, (n_steps,) + shape)

    def _run_nan_policy(self, series: dict, buffers: dict, nan: str) -> dict:
        """NaN policy and finiteness for a run: every used component must be finite ("raise"),
        or non-finite components are masked ("mask"); masked components are zeroed."""
        if "z" not in series:
            return series
        z, mask = series["z"], series["mask"]
        finite = np.isfinite(z)
        per_component = mask.shape == z.shape
        used = mask > 0.5 if per_component else np.broadcast_to(mask > 0.5, z.shape)
        if nan == "mask":
            mask = mask * (finite if per_component else finite.all(axis=1, keepdims=True))
        elif np.any(used & ~finite):
            rows = np.flatnonzero(np.any(used & ~finite, axis=1))
            raise ValueError(f"z: NaN/Inf in used components at steps {rows[:10].tolist()}; pass nan='mask' to skip them")
        for key, value in series.items():
            if key not in ("z", "mask") and not np.isfinite(value).all():
                raise ValueError(f"{key}: contains NaN or Inf")
        series["mask"] = mask
        keep = mask > 0.5 if per_component else np.broadcast_to(mask > 0.5, z.shape)
        series["z"] = np.where(keep, z, self._masked_fill(buffers))
        return series

    @staticmethod
    def _masked_fill(buffers: dict) -> np.ndarray | float:
        return 0.0

    def _run(self, name: str, per_step: dict, n_steps: int) -> RunResult:
        """The run loop, written once: the C ``<kernel>_run`` or, on the VM backend, step by step
        (the filter's run kernel, ``FilterSpec.run``, else its step kernel)."""
        kernel = self.spec.run.get(name, self.spec.step[name])
        info = self._backend.kernels[kernel]
        constants = self._measurement_buffers(name)
        dtype = self._dtype
        for n in info.per_step:
            self._fits(n, per_step[n])
        arrays = [np.ascontiguousarray(per_step[n], dtype=dtype) if n in info.per_step
                  else np.asfortranarray(constants[n], dtype=dtype) for n, _ in info.inputs]
        histories = {n: np.zeros((n_steps,) + self._buffers[n].shape[::-1], dtype) for n in self.spec.state}
        status = np.zeros(n_steps, dtype=np.intc)
        self._before_write()
        run = self._backend.run_function(kernel)
        if run is not None:
            run(n_steps, *[a.ctypes.data for a in arrays], *[histories[n].ctypes.data for n in self.spec.state],
                status.ctypes.data)
        else:
            self._run_in_python(kernel, info, arrays, histories, status)
        if n_steps:
            for n in self.spec.state:
                self._buffers[n][...] = histories[n][-1].T
            self.t = float(per_step["t"][-1] + per_step["dt"][-1]) if "t" in per_step else \
                self.t + float(np.sum(per_step["dt"]))
        x = histories["x"]
        P = np.transpose(histories["P"], (0, 2, 1)) if "P" in histories else None
        if self._scaling is not None:
            x, P = self._scaling.x_from_kernel(x), None if P is None else self._scaling.P_from_kernel(P)
        return RunResult(np.asarray(x, dtype=float), None if P is None else np.asarray(P, dtype=float), status)

    def _run_in_python(self, kernel, info, arrays, histories, status) -> None:
        """The run loop for the VM backend: the same kernel, step by step, on scratch buffers."""
        buffers = {n: _buffer(shape, self._dtype) for n, shape in info.inputs + info.outputs[:-1]}
        for (n, _), array in zip(info.inputs, arrays):
            if n not in info.per_step:
                buffers[n].reshape(-1, order="F")[:] = array.reshape(-1, order="F")
        call = self._backend.bind(kernel, buffers)
        for k in range(status.size):
            for (n, _), array in zip(info.inputs, arrays):
                if n in info.per_step:
                    buffers[n].reshape(-1, order="F")[:] = array[k].reshape(-1)
            status[k] = call()
            for n, history in histories.items():
                history[k] = buffers[n].T


#: Older name of :class:`Filter` (the launcher's EKF/UKF are plain Filters).
KalmanFilter = Filter


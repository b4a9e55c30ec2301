"""One filter object for every generated filter, built from the manifest's filter spec.

A :class:`Filter` reads its :class:`~symkf.codegen.spec.FilterSpec` (which kernel predicts,
updates and steps with each measurement, which outputs are the carried state and which are
diagnostics, default scalars), makes one numpy buffer per argument of those kernels
(:mod:`symkf.runtime.buffers`), binds every kernel to them once, and exposes ``x``, ``P`` and the
diagnostics ``y``/``S`` as read-only views, FilterPy-style. ``predict``, ``update`` and ``step``
are one kernel call each; ``run`` is the whole loop in C (or, on the CasADi-VM backend, the same
kernel called step by step; :mod:`symkf.runtime.runs`).

Every call enforces :mod:`symkf.runtime.contract` before it writes a buffer; the kernels write
x and P only on success, so when anything raises, x, P and t are bit-identical to before.

The C fast path of :meth:`Filter.step` and its trusted-step replay are the filter's
:class:`~symkf.runtime.fastpath.FastPath`; every write from Python goes through its
``before_write``. A scaled build converts x, P (and Q) at the boundary
(:class:`~symkf.runtime.state_scaling.StateScaling`).
"""
from __future__ import annotations

from copy import deepcopy

import numpy as np

from symkf.codegen.spec import FilterSpec
from . import calls, contract, multi_runs, runs, smoothing
from .buffers import fits, kernel_roles, make_buffers
from .contract import covariance, read_only
from .fastpath import FastPath
from .runs import RunResult
from .state_scaling import StateScaling


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
        self._buffers, self.measurements = make_buffers(self.spec, self.kernels, self._dtype)
        self._fast = FastPath(self)         # its data made with the buffers, its calls bound by _bind
        self.n = self._buffers["x"].size
        self._views = {name: read_only(self._buffers[name]) for name in ("x", "P") if name in self._buffers}
        calls.initialise(self, x0, P0, Q, R, p, gate, scalars)
        self.t = 0.0
        self._default = self.spec.measurements[0]
        self._bind()

    # ------------------------------------------------------------------ copies
    #: What a copy shares with its original: the compiled model and what describes it (read only).
    _SHARED = frozenset({"spec", "family", "model", "_backend", "kernels", "_dtype", "_scaling"})
    #: What a copy binds afresh: calls into the C library hold pointers to the original's buffers.
    _BOUND = frozenset({"step", "_calls", "_fast", "_views"})

    def copy(self) -> "Filter":
        """An independent filter at this filter's state (x, P, t, noises, gates, options): stepping
        either leaves the other as it was. ``copy.copy`` and ``copy.deepcopy`` give the same."""
        clone = object.__new__(type(self))
        clone.__dict__.update({key: value if key in self._SHARED else deepcopy(value)
                               for key, value in self.__dict__.items() if key not in self._BOUND})
        clone._views = {name: read_only(clone._buffers[name]) for name in self._views}
        clone._fast = self._fast.copy()
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
    def _measurement_buffers(self, name: str) -> dict[str, np.ndarray]:
        """Every buffer a kernel of measurement ``name`` reads or writes, by argument name."""
        return {**self._buffers, **self.measurements[name]}

    def _bind(self) -> None:
        self._calls = {kernel: self._backend.bind(kernel, self._buffers if measurement is None
                                                  else self._measurement_buffers(measurement))
                       for kernel, measurement in kernel_roles(self.spec)}
        self._fast.bind(self, Filter.step)

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
        return self._fast.calls

    @property
    def fast_path(self) -> bool:
        """Whether plain ``step`` calls take the C fast path. Set False to send every call through
        the Python contract (same results; for comparisons), True to restore it."""
        return self._fast.default is not None

    @fast_path.setter
    def fast_path(self, on: bool) -> None:
        if on:
            self._fast.switch_on()
        else:
            self._fast.switch_off()

    def kernel_buffer(self, name: str, measurement: str | None = None) -> np.ndarray:
        """The writable buffer a bound kernel reads (no checks: for benchmarks that restore the
        state between timed kernel calls)."""
        self._fast.before_write()
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
        value = fits(self._dtype, name, value, " after scaling" if self._scaling is not None else "")
        self._fast.before_write()
        self._buffers[name][:] = value

    @property
    def p(self) -> np.ndarray:
        return read_only(self._buffers["p"])

    @p.setter
    def p(self, value) -> None:
        value = fits(self._dtype, "p", contract.finite_array("p", value, self._buffers["p"].shape))
        self._fast.before_write()
        self._buffers["p"][:] = value

    def R(self, measurement: str | None = None) -> np.ndarray:
        return read_only(self._measurement(measurement)["R"])

    def set_R(self, measurement: str, value) -> None:
        """Measurement noise covariance (symmetric positive definite)."""
        buffers = self._measurement(measurement)
        name = f"R[{measurement}]"
        value = fits(self._dtype, name, covariance(name, value, buffers["R"].shape[0], definite=True))
        self._fast.before_write()
        buffers["R"][:] = value

    def set_gate(self, measurement: str, probability: float | None = None, threshold: float | None = None) -> None:
        """Chi-square innovation gate: an update whose y^T S^-1 y exceeds the ``probability``
        quantile of chi2(k) (k = used components), or ``threshold``, is skipped (state unchanged,
        status SYMKF_GATED). Neither given: no gate (the default)."""
        buffers = self._measurement(measurement)
        if "gate" not in buffers:
            raise ValueError(f"gate: filter '{self.family}' has no innovation gate")
        gate = contract.gate(probability, threshold, buffers["gate"].size)
        self._fast.before_write()
        buffers["gate"][:] = gate

    def y(self, measurement: str | None = None) -> np.ndarray:
        """Innovation of the last update with ``measurement``."""
        return self._diagnostic("y", measurement)

    def S(self, measurement: str | None = None) -> np.ndarray:
        """Innovation covariance of the last update with ``measurement``."""
        return self._diagnostic("S", measurement)

    def _diagnostic(self, key: str, measurement: str | None) -> np.ndarray:
        name = self._default if measurement is None else measurement
        self._measurement(name)
        return self._fast.diagnostic(key, name)

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
        t, dt, u = contract.real("t", t), contract.time_step(dt), calls.u_input(self, u)
        calls.write_time(self, t, dt, u)
        calls.check(self, self._calls[self.spec.predict](), "predict")
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
        name = calls.measurement_name(self, measurement, "update")
        values = calls.measurement_values(self, name, {"z": z, "q": q, "mask": mask}, nan)
        t = self.t if t is None else contract.real("t", t)
        u = calls.u_input(self, u)
        calls.write_time(self, t, None, u)
        calls.write_measurement(self, name, values)
        return calls.check(self, self._calls[self.spec.update[name]](), f"update '{name}'", name)

    def step(self, t: float, dt: float, z, measurement: str | None = None, q=None, mask=None,
             u=None, nan: str = "raise") -> int:
        """predict(t, dt) then update(z) at t + dt — one call into the compiled code. Returns 0
        or SYMKF_GATED (prediction applied, update refused by the gate)."""
        paths = self._fast
        fast = paths.default if measurement is None else paths.steps.get(measurement) if type(measurement) is str else None
        if fast is not None and nan == "raise":
            code = fast(t, dt, z, q, mask, u)     # sets self.t; None: not a plain call, the Python path decides
            if code is not None:
                return code
        name = calls.measurement_name(self, measurement, "step")
        values = calls.measurement_values(self, name, {"z": z, "q": q, "mask": mask}, nan)
        t = self.t if t is None else contract.real("t", t)
        dt, u = contract.time_step(dt), calls.u_input(self, u)
        calls.write_time(self, t, dt, u)
        calls.write_measurement(self, name, values)
        code = calls.check(self, self._calls[self.spec.step[name]](), f"step '{name}'", name)
        self.t = t + dt
        return code

    # ------------------------------------------------------------------ whole runs
    def run(self, times, z, measurement: str | None = None, q=None, mask=None, u=None,
            nan: str = "raise", smooth: bool = False) -> RunResult:
        """Filter a whole record in one compiled call: step k predicts from times[k-1] to times[k]
        (the first step has dt = 0) and updates with z[k]. The filter's x, P and t end at the last
        step. A step that fails keeps the state and records its code in ``status``.

        Args:
            times: (N,) strictly increasing; z: (N, m); q: (N, nq) or (nq,); mask: (N, m) or None;
            u: (N, nu) or (nu,) or None (the current input held).
            smooth: also smooth the run (fixed-interval, :func:`symkf.runtime.smoothing.smooth`):
                a SmoothedRun with ``x_smooth``, ``P_smooth`` beside the filtered x, P.
        """
        name = calls.measurement_name(self, measurement, "step")
        times = contract.run_times(times)
        per_step = {"t": np.concatenate([times[:1], times[:-1]]), "dt": np.diff(times, prepend=times[:1])}
        result = runs.run(self, name, per_step, {"z": z, "q": q, "mask": mask}, u, nan)
        return smoothing.smooth(self, result) if smooth else result

    def run_multi(self, times, z: dict, q: dict | None = None, mask: dict | None = None, u=None,
                  nan: str = "raise"):
        """:meth:`run` over a record of several measurements ({name: array}), in one compiled call:
        :func:`symkf.runtime.multi_runs.run_multi`."""
        return multi_runs.run_multi(self, times, z, q, mask, u, nan)

    def run_steps(self, dt, z, measurement: str | None = None, q=None, mask=None, u=None,
                  nan: str = "raise", smooth: bool = False) -> RunResult:
        """:meth:`run` given step lengths from the filter's time: step k predicts over dt[k] (> 0;
        the first may be 0) and updates with z[k]; arguments as :meth:`run`."""
        name = calls.measurement_name(self, measurement, "step")
        dt = contract.run_steps(dt)
        per_step = {"t": self.t + np.concatenate([[0.0], np.cumsum(dt)])[:-1], "dt": dt}
        result = runs.run(self, name, per_step, {"z": z, "q": q, "mask": mask}, u, nan)
        return smoothing.smooth(self, result) if smooth else result

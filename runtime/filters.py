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
from . import calls, contract, lockstep_runs, multi_runs, runs, smoothing
from .buffers import fits, kernel_roles, make_buffers
from .contract import DEFAULT_GATE_PROBABILITY, read_only
from .covariance_form import CholeskyForm
from .fastpath import FastPath
from .filter_state import FilterState
from .runs import RunResult
from .state_scaling import StateScaling


__all__ = ["DEFAULT_GATE_PROBABILITY", "Filter"]


class Filter(FilterState):
    """A generated filter (EKF, UKF, continuous-discrete EKF, ...) of one compiled model.

    Args:
        compiled: a :class:`~symkf.runtime.CompiledModel`.
        spec: the filter's name in the manifest (``compiled.filters``) or its FilterSpec.
        x0: initial state, the model's states in declaration order and units (a quaternion state
            as its 4 scalar-last components, unit norm).
        P0: initial covariance (symmetric positive semi-definite), in the filter's chart
            (``filter.chart`` says which): for "ekf", "ukf", "cd_ekf" the n x n covariance of x
            itself; for the manifold filters ("mekf", "mukf", "sukf", "aukf") the covariance of
            the error state, n - 1 per quaternion square: each quaternion's 4 components are one
            3-vector rotation error in the build's chart (codegen option ``manifold_chart``):
            "rotation_vector" (the default: rad, the small angle about each axis) or
            "vector_part" (paper 000, models/attitude.py: the error quaternion's vector part,
            |dp| = sin(angle / 2), half the angle: a P0 given in rad^2 of rotation angle is 4x
            too large in this chart).
        Q: process-noise power spectral density, symmetric PSD, in the same chart as P0: n x n
            (error-state for manifold filters), additive (discrete noise Q dt), or, for a model
            that declares noise(), nw x nw of its noises w (discrete noise G Q G^T dt, G = df/dw at
            the step start; see codegen/families/kalman.py).
        R: {measurement: covariance} (symmetric PD); default diag(sigma^2) from the model.
        p: runtime parameters (default: the model's defaults).
        gate: {measurement: probability in (0, 1), {"threshold": value} or None (no gate)}
            chi-square innovation gates, or "none" (no gate at all); a measurement not given
            gets the default gate,
            :data:`DEFAULT_GATE_PROBABILITY` (a consistent filter refuses about one update in
            10^9; a gross outlier, e.g. a range of 1e30 m, is refused, status SYMKF_GATED).
        t0: the filter's time at x0 (its clock; every call's t must agree with it).
        **scalars: scalar inputs of the kernels, e.g. ``kappa`` (defaults from the spec).

    A model with several measurements needs the measurement named on every ``update``/``step``/
    ``run``; a model with inputs needs ``u`` on every call that reads it (``u="hold"`` keeps the
    last input on purpose); a call's ``t`` must be the filter's time (None: that time). Every call
    that raises leaves x, P and t as they were.

    ``step(t, dt, z, q=...)`` with float64 arrays of the right shape takes a fast path: the
    contract's checks, the copies and the kernel call in one C call (:mod:`symkf.runtime.fastcall`);
    any other call, and every error, takes the Python path below, with the same rules.
    """

    def __init__(self, compiled, spec, x0, P0=None, Q=None, R: dict | None = None, p=None,
                 gate: dict | None = None, t0: float = 0.0, **scalars):
        self.spec: FilterSpec = compiled.filters[spec] if isinstance(spec, str) else spec
        self.family = self.spec.name
        self.model = compiled.model
        self._backend = compiled.backend
        self._clock = np.zeros(1)           # the filter's time t (the fast path of step sets it in C)
        self.kernels = {name: self._backend.kernels[name] for name in self.spec.kernel_names()}
        self._dtype = getattr(self._backend, "dtype", np.dtype(np.float64))
        self._scaling = StateScaling.of(self.model)
        self._form = CholeskyForm.of(self.spec)     # None: the kernels carry P itself, else its factor
        self._buffers, self.measurements = make_buffers(self.spec, self.kernels, self._dtype)
        self._fast = FastPath(self)         # its data made with the buffers, its calls bound by _bind
        self.n = self._buffers["x"].size
        self._views = {name: read_only(self._buffers[name]) for name in ("x", "P") if name in self._buffers}
        self._default_gates: set[str] = set()    # measurements gated by DEFAULT_GATE_PROBABILITY
        self._u_given = False                    # whether any call gave u (an update may then hold it)
        calls.initialise(self, x0, P0, Q, R, p, gate, scalars)
        self.t = t0
        # the measurement of a call that names none: only a filter with one has it
        self._default = self.spec.measurements[0] if len(self.spec.measurements) == 1 else None
        self._bind()

    # ------------------------------------------------------------------ copies
    #: What a copy shares with its original: the compiled model and what describes it (read only).
    _SHARED = frozenset({"spec", "family", "model", "_backend", "kernels", "_dtype", "_scaling", "_form"})
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
        """The filter's time: the end of its last step (or as set). Setting it restarts the clock
        there without propagating (e.g. after re-initialising x and P for that time)."""
        return float(self._clock[0])

    @t.setter
    def t(self, value) -> None:
        self._clock[0] = fits(self._dtype, "t", contract.real("t", value))

    @property
    def fast_calls(self) -> int:
        """How many calls of ``step`` took the C fast path (since it was last switched on)."""
        return self._fast.calls

    @property
    def fast_path(self) -> bool:
        """Whether plain ``step`` calls take the C fast path. Set False to send every call through
        the Python contract (same results; for comparisons), True to restore it."""
        return any(step is not None for step in self._fast.steps.values())

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
        return self._calls[getattr(self.spec, kind)[calls.measurement_name(self, measurement, kind)]]

    # ------------------------------------------------------------------ steps
    def predict(self, t: float | None, dt: float, u=None) -> None:
        """Propagate from time t (the filter's time, or None for it) to t + dt with input u."""
        if not self.spec.predict:
            raise ValueError(f"predict: filter '{self.family}' only steps (it has no separate prediction)")
        dt = contract.time_step(dt)
        t = self.t if t is None else contract.on_clock(t, self.t, dt, "predict")
        u = calls.u_input(self, u, "predict")
        calls.write_time(self, t, dt, u)
        calls.check(self, self._calls[self.spec.predict](), "predict")
        self.t = t + dt

    def update(self, z, measurement: str | None = None, q=None, mask=None, t: float | None = None,
               u=None, nan: str = "raise") -> int:
        """Update with measurement z taken at the filter's time (``t``, if given, must be it).

        Args:
            measurement: its name (required when the model has more than one).
            q: the measurement's runtime parameters (required when it has any).
            mask: 1/0 per component; 0 ignores that component.
            nan: "raise" (a NaN/Inf component is an error) or "mask" (it is skipped).
        Returns:
            0, or SYMKF_GATED if the innovation gate refused the update (state unchanged).
        """
        name = calls.measurement_name(self, measurement, "update")
        values = calls.measurement_values(self, name, {"z": z, "q": q, "mask": mask}, nan)
        t = self.t if t is None else contract.on_clock(t, self.t, 0.0, "update")
        u = calls.u_input(self, u, "update", calls.reads_u(self, self.spec.update[name]))
        calls.write_time(self, t, None, u)
        calls.write_measurement(self, name, values)
        return calls.check(self, self._calls[self.spec.update[name]](), f"update '{name}'", name)

    def step(self, t: float, dt: float, z, measurement: str | None = None, q=None, mask=None,
             u=None, nan: str = "raise") -> int:
        """predict(t, dt) then update(z) at t + dt — one call into the compiled code. t is the
        filter's time (None: that time); the measurement's name is required when the model has
        several, u when it has inputs. Returns 0 or SYMKF_GATED (prediction applied, update
        refused by the gate)."""
        paths = self._fast
        fast = paths.default if measurement is None else paths.steps.get(measurement) if type(measurement) is str else None
        if fast is not None and nan == "raise":
            code = fast(t, dt, z, q, mask, u)     # sets self.t; None: not a plain call, the Python path decides
            if code is not None:
                return code
        name = calls.measurement_name(self, measurement, "step")
        values = calls.measurement_values(self, name, {"z": z, "q": q, "mask": mask}, nan)
        dt = contract.time_step(dt)
        t = self.t if t is None else contract.on_clock(t, self.t, dt, "step")
        u = calls.u_input(self, u, "step")
        calls.write_time(self, t, dt, u)
        calls.write_measurement(self, name, values)
        code = calls.check(self, self._calls[self.spec.step[name]](), f"step '{name}'", name)
        self.t = t + dt
        return code

    # ------------------------------------------------------------------ whole runs
    def run(self, times, z, measurement: str | None = None, q=None, mask=None, u=None,
            nan: str = "raise", refused: str = "raise", smooth: bool = False) -> RunResult:
        """Filter a whole record in one compiled call: step k predicts from times[k-1] to times[k]
        (step 0 from the filter's time, dt = 0 if times[0] is that time) and updates with z[k].
        The filter's x, P and t end at the last step.

        Args:
            times: (N,) strictly increasing, times[0] not before the filter's time; z: (N, m);
            measurement: its name (required when the model has more than one);
            q: (N, nq) or (nq,); mask: (N, m) or None;
            u: (N, nu) or (nu,) (required when the model has inputs; "hold": the current input);
            refused: "raise" (default): if any step is refused (a SYMKF_ERR_* code: that step kept
                the state while time went on), raise :class:`~symkf.runtime.runs.RunRefused` with
                the run's result attached and leave the filter as it was; "continue": return the
                result, whose ``refused_steps`` and ``counts`` (shown by its repr) say which.
            smooth: also smooth the run (fixed-interval, :func:`symkf.runtime.smoothing.smooth`):
                a SmoothedRun with ``x_smooth``, ``P_smooth`` beside the filtered x, P.
        """
        name = calls.measurement_name(self, measurement, "step", "run")
        times = contract.run_times(times)
        per_step = runs.steps_from_clock(self, times, "run")
        result = runs.run(self, name, per_step, {"z": z, "q": q, "mask": mask}, u, nan, refused)
        return smoothing.smooth(self, result) if smooth else result

    def run_multi(self, times, z: dict, q: dict | None = None, mask: dict | None = None, u=None,
                  nan: str = "raise", refused: str = "raise"):
        """:meth:`run` over a record of several measurements ({name: array}), in one compiled call:
        :func:`symkf.runtime.multi_runs.run_multi`."""
        return multi_runs.run_multi(self, times, z, q, mask, u, nan, refused)

    def run_lockstep(self, times, z, measurement: str | None = None, q=None, mask=None, u=None,
                     nan: str = "raise", refused: str = "raise") -> list:
        """Monte Carlo runs over one clock, one per z[r] (z: (runs, N, m)), each from the filter's
        x, P and t, which stay as they are: a list of RunResults, each what :meth:`run` returns for
        that run, bit for bit, computed 4 runs at a time where the library has the lockstep loop
        (:func:`symkf.runtime.lockstep_runs.run_lockstep`); a library built with
        ``<family>_lockstep_vector_math`` differs from :meth:`run` by libmvec's round-off."""
        return lockstep_runs.run_lockstep(self, times, z, measurement, q, mask, u, nan, refused)

    def run_steps(self, dt, z, measurement: str | None = None, q=None, mask=None, u=None,
                  nan: str = "raise", refused: str = "raise", smooth: bool = False) -> RunResult:
        """:meth:`run` given step lengths from the filter's time: step k predicts over dt[k] (> 0;
        the first may be 0) and updates with z[k]; arguments as :meth:`run`."""
        name = calls.measurement_name(self, measurement, "step", "run_steps")
        dt = contract.run_steps(dt)
        per_step = {"t": self.t + np.concatenate([[0.0], np.cumsum(dt)])[:-1], "dt": dt}
        result = runs.run(self, name, per_step, {"z": z, "q": q, "mask": mask}, u, nan, refused)
        return smoothing.smooth(self, result) if smooth else result

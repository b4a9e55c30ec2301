"""FilterPy-shaped filter objects over the generated kernels.

A filter owns numpy buffers (``x``, ``P``, ``Q``, per measurement ``z``, ``R``, ``y``, ``S``...)
that the kernels read and write in place; ``predict``, ``update`` and ``step`` are one kernel
call each. After an update, ``y`` (innovation) and ``S`` (its covariance) of that measurement are
inspectable, as in FilterPy.

Bad input never corrupts the state: shapes are checked before any buffer is touched, and the C
code writes x and P only on success. A failure raises :class:`SymkfError` naming the code.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from symkf.codegen.spec import STATUS_NONFINITE
from .backends import SymkfError



def _matrix(shape) -> np.ndarray:
    return np.zeros(shape, order="F")


def _exact_array(name: str, value, target: np.ndarray) -> np.ndarray:
    """``value`` as float64 of exactly ``target``'s shape (fast for ndarrays; hot path)."""
    if type(value) is np.ndarray and value.dtype is target.dtype and value.shape == target.shape:
        return value
    return as_array(name, value, target.shape)


def as_array(name: str, value, shape: tuple[int, ...]) -> np.ndarray:
    """``value`` as a float array of exactly ``shape``; ValueError names the argument otherwise."""
    try:
        array = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected numbers of shape {shape}, got {type(value).__name__}") from None
    if array.shape != shape:
        if array.size == int(np.prod(shape)) and array.ndim <= 1 and len(shape) == 1:
            array = array.reshape(shape)
        else:
            raise ValueError(f"{name}: expected shape {shape}, got {array.shape}")
    return array


def read_only(array: np.ndarray) -> np.ndarray:
    """A read-only view of a buffer the C code writes (users inspect it, never assign into it)."""
    view = array.view()
    view.flags.writeable = False
    return view


def covariance(name: str, value, n: int) -> np.ndarray:
    """``value`` as an n x n covariance: finite, symmetric and positive definite, else ValueError."""
    value = as_array(name, value, (n, n))
    if not np.isfinite(value).all():
        raise ValueError(f"{name}: contains NaN or Inf")
    if not np.allclose(value, value.T, rtol=1e-12, atol=0):
        raise ValueError(f"{name}: not symmetric")
    try:
        np.linalg.cholesky(value)
    except np.linalg.LinAlgError:
        raise ValueError(f"{name}: not positive definite") from None
    return value


@dataclass
class MeasurementBuffers:
    """Per-measurement buffers shared by the update and step kernels of one filter."""

    q: np.ndarray
    z: np.ndarray
    mask: np.ndarray
    R: np.ndarray
    y: np.ndarray
    S: np.ndarray


@dataclass
class RunResult:
    """A whole run: state and covariance after every step, and each step's status code."""

    x: np.ndarray          # (n_steps, n)
    P: np.ndarray          # (n_steps, n, n)
    status: np.ndarray     # (n_steps,) int

    @property
    def failed_steps(self) -> np.ndarray:
        return np.flatnonzero(self.status)


class KalmanFilter:
    """EKF or UKF (``family``) of one compiled model.

    Args:
        compiled: a :class:`~symkf.runtime.CompiledModel`.
        family: "ekf" or "ukf".
        x0, P0: initial state and covariance.
        Q: process-noise power spectral density: n x n, additive (discrete noise Q dt), or, for a
            model that declares noise(), nw x nw of its noises w (discrete noise G Q G^T dt,
            G = df/dw at the step start; see codegen/families/kalman.py).
        R: {measurement: covariance}; defaults to diag(sigma^2) from the model.
        p: runtime parameters (default: the model's defaults).
        kappa: UKF scaling (Julier); ignored by the EKF.
    """

    def __init__(self, compiled, family: str, x0, P0, Q, R: dict | None = None, p=None, kappa: float = 0.0):
        self.model = compiled.model
        self.family = family
        n = len(self.model["states"])
        self.n = n
        self._buffers = {"t": np.zeros(1), "dt": np.zeros(1), "x": np.zeros(n), "P": _matrix((n, n)),
                         "u": np.zeros(len(self.model["inputs"])), "p": np.zeros(len(self.model["params"])),
                         "Q": _matrix(dict(compiled.backend.kernels[f"{family}_predict"].inputs)["Q"]),
                         "kappa": np.array([float(kappa)])}
        self._buffers["p"][:] = [q["default"] for q in self.model["params"]] if p is None else \
            as_array("p", p, (len(self.model["params"]),))
        self.x = x0
        self.P = P0
        self.Q = Q
        self.t = 0.0
        self.measurements: dict[str, MeasurementBuffers] = {}
        R = R or {}
        for name, meas in self.model["measurements"].items():
            m, nq = len(meas["outputs"]), len(meas["params"])
            buffers = MeasurementBuffers(np.zeros(nq), np.zeros(m), np.ones(m), _matrix((m, m)),
                                         np.zeros(m), _matrix((m, m)))
            buffers.R[:] = as_array(f"R[{name}]", R[name], (m, m)) if name in R else np.diag(np.square(meas["sigma"]))
            self.measurements[name] = buffers
        self._default_measurement = next(iter(self.measurements), None)
        self._mask_dirty = False
        self._t_buffer, self._dt_buffer = self._buffers["t"], self._buffers["dt"]
        self._bind(compiled)

    # ------------------------------------------------------------------ binding
    def _bind(self, compiled) -> None:
        backend = compiled.backend
        self._predict_call = backend.bind(f"{self.family}_predict", self._buffers)
        self._update_calls, self._step_calls = {}, {}
        for name, buffers in self.measurements.items():
            merged = {**self._buffers, **vars(buffers)}
            self._update_calls[name] = backend.bind(f"{self.family}_update_{name}", merged)
            self._step_calls[name] = backend.bind(f"{self.family}_step_{name}", merged)
        self._backend = backend

    def kernel_call(self, kind: str, measurement: str | None = None):
        """The bound compiled call behind ``predict``/``update``/``step`` (no argument checks):
        for benchmarks that time the C call alone. Returns a callable giving the status code."""
        if kind == "predict":
            return self._predict_call
        calls = {"update": self._update_calls, "step": self._step_calls}[kind]
        return calls[measurement or self._default_measurement]

    # ------------------------------------------------------------------ state views
    @property
    def x(self) -> np.ndarray:
        """The state estimate (a read-only view of the buffer the C code writes)."""
        return read_only(self._buffers["x"])

    @x.setter
    def x(self, value) -> None:
        value = as_array("x", value, (self.n,))
        if not np.isfinite(value).all():
            raise ValueError("x: contains NaN or Inf")
        self._buffers["x"][:] = value

    @property
    def P(self) -> np.ndarray:
        return read_only(self._buffers["P"])

    @P.setter
    def P(self, value) -> None:
        self._buffers["P"][:] = covariance("P", value, self.n)

    @property
    def Q(self) -> np.ndarray:
        return self._buffers["Q"]

    @Q.setter
    def Q(self, value) -> None:
        value = as_array("Q", value, self._buffers["Q"].shape)
        if not np.isfinite(value).all():
            raise ValueError("Q: contains NaN or Inf")
        self._buffers["Q"][:] = value

    @property
    def p(self) -> np.ndarray:
        return self._buffers["p"]

    def R(self, measurement: str | None = None) -> np.ndarray:
        return self.measurements[measurement or self._default_measurement].R

    def y(self, measurement: str | None = None) -> np.ndarray:
        """Innovation of the last update with ``measurement``."""
        return self.measurements[measurement or self._default_measurement].y

    def S(self, measurement: str | None = None) -> np.ndarray:
        """Innovation covariance of the last update with ``measurement``."""
        return self.measurements[measurement or self._default_measurement].S

    # ------------------------------------------------------------------ steps
    def predict(self, t: float, dt: float, u=None) -> None:
        """Propagate from time t to t + dt."""
        self._t_buffer[0] = t
        self._dt_buffer[0] = dt
        if u is not None:
            self._set_input(u)
        code = self._predict_call()
        if code:
            self._raise(code, "predict")
        self.t = t + dt

    def update(self, z, measurement: str | None = None, q=None, mask=None, t: float | None = None,
               u=None, nan: str = "raise") -> None:
        """Update with measurement z taken at time t (default: the time of the last predict).

        Args:
            q: the measurement's runtime parameters (e.g. a radar station's coordinates).
            mask: 1/0 per component; 0 ignores that component.
            nan: "raise" (a NaN/Inf component is an error) or "mask" (it is ignored).
        """
        name = measurement or self._default_measurement
        buffers = self._prepare_measurement(name, z, q, mask, nan)
        self._t_buffer[0] = self.t if t is None else t
        if u is not None:
            self._set_input(u)
        code = self._update_calls[name]()
        if code:
            self._raise(code, f"update '{name}'", buffers)

    def step(self, t: float, dt: float, z, measurement: str | None = None, q=None, mask=None,
             u=None, nan: str = "raise") -> None:
        """predict(t, dt) then update(z) at t + dt — one call into the compiled code."""
        name = measurement or self._default_measurement
        buffers = self._prepare_measurement(name, z, q, mask, nan)
        self._t_buffer[0] = t
        self._dt_buffer[0] = dt
        if u is not None:
            self._set_input(u)
        code = self._step_calls[name]()
        if code:
            self._raise(code, f"step '{name}'", buffers)
        self.t = t + dt

    # ------------------------------------------------------------------ helpers
    def _set_input(self, u) -> None:
        self._buffers["u"][:] = as_array("u", u, self._buffers["u"].shape)

    def _prepare_measurement(self, name: str, z, q, mask, nan: str) -> MeasurementBuffers:
        """Validate, then copy z (and q, mask) into the buffers; nothing is written on error."""
        buffers = self.measurements.get(name)
        if buffers is None:
            raise ValueError(f"measurement: '{name}' is not one of {list(self.measurements)}")
        z_array = _exact_array("z", z, buffers.z)
        if mask is not None or nan != "raise" or self._mask_dirty:
            new_mask = self._new_mask(buffers, z_array, mask, nan)
        else:
            new_mask = None
        if q is not None:
            buffers.q[...] = _exact_array("q", q, buffers.q)
        buffers.z[...] = z_array
        if new_mask is not None:
            buffers.mask[...] = new_mask
            self._mask_dirty = not bool(new_mask.all())
        return buffers

    def _new_mask(self, buffers: MeasurementBuffers, z: np.ndarray, mask, nan: str) -> np.ndarray:
        new_mask = np.ones_like(buffers.mask) if mask is None else as_array("mask", mask, buffers.mask.shape)
        if not np.isin(new_mask, (0.0, 1.0)).all():
            raise ValueError("mask: entries must be 0 or 1")
        if nan == "mask":
            new_mask = new_mask * np.isfinite(z)
        elif nan != "raise":
            raise ValueError("nan: expected 'raise' or 'mask'")
        return new_mask

    def _raise(self, code: int, what: str, buffers: MeasurementBuffers | None = None) -> None:
        detail = ""
        if code == STATUS_NONFINITE and buffers is not None:
            bad = ~np.isfinite(buffers.z) & (buffers.mask > 0.5)
            if bad.any():
                detail = f"measurement z has NaN/Inf at components {np.flatnonzero(bad).tolist()}; pass nan='mask' to skip them"
        raise SymkfError(f"{self.family} {what}", code, detail)

    # ------------------------------------------------------------------ whole runs
    def run(self, times, z, measurement: str | None = None, q=None, mask=None, u=None) -> RunResult:
        """Filter a whole record in one compiled call: step k predicts from times[k-1] to times[k]
        (the first step has dt = 0) and updates with z[k]. The filter's x, P end at the last step.

        Args:
            times: (N,) measurement times; z: (N, m); q: (N, nq) or (nq,); mask: (N, m) or None.
        """
        name = measurement or self._default_measurement
        meas = self.measurements[name]
        times = np.asarray(times, dtype=float)
        n_steps = times.size
        per_step = {
            "t": np.concatenate([[times[0]], times[:-1]]) if n_steps else times,
            "dt": np.diff(times, prepend=times[:1]) if n_steps else times,
            "z": as_array("z", z, (n_steps, meas.z.size)),
            "mask": np.ones((n_steps, meas.z.size)) if mask is None else as_array("mask", mask, (n_steps, meas.z.size)),
            "q": np.broadcast_to(meas.q if q is None else np.asarray(q, float), (n_steps, meas.q.size)),
            "u": np.broadcast_to(self._buffers["u"] if u is None else np.asarray(u, float),
                                 (n_steps, self._buffers["u"].size)),
        }
        per_step["z"] = np.where(per_step["mask"] > 0.5, per_step["z"], 0.0)
        constants = {**self._buffers, "R": meas.R}
        return self._run_kernel(f"{self.family}_step_{name}", per_step, constants, n_steps)

    def _run_kernel(self, kernel: str, per_step: dict, constants: dict, n_steps: int) -> RunResult:
        info = self._backend.kernels[kernel]
        n = self.n
        x_hist, P_hist = np.zeros((n_steps, n)), np.zeros((n_steps, n, n))
        status = np.zeros(n_steps, dtype=np.intc)
        run = self._backend.run_function(kernel)
        arrays = []
        for name, shape in info.inputs:
            if name in info.per_step:
                arrays.append(np.ascontiguousarray(per_step[name], dtype=float))
            else:
                arrays.append(np.asfortranarray(constants[name], dtype=float))
        if run is not None:
            run(n_steps, *[a.ctypes.data for a in arrays], x_hist.ctypes.data, P_hist.ctypes.data,
                status.ctypes.data)
        else:
            self._run_in_python(kernel, info, arrays, x_hist, P_hist, status)
        if n_steps:
            self._buffers["x"][:] = x_hist[-1]
            self._buffers["P"][:] = P_hist[-1].T
            self.t = float(per_step["t"][-1] + per_step["dt"][-1])
        return RunResult(x_hist, np.transpose(P_hist, (0, 2, 1)), status)

    def _run_in_python(self, kernel, info, arrays, x_hist, P_hist, status) -> None:
        """The run loop for the VM backend: the same kernel, step by step."""
        buffers = {name: np.zeros(shape, order="F") for name, shape in info.inputs + info.outputs[:-1]}
        for (name, shape), array in zip(info.inputs, arrays):
            if name not in info.per_step:
                buffers[name].reshape(-1, order="F")[:] = array.reshape(-1, order="F")
        call = self._backend.bind(kernel, buffers)
        for k in range(status.size):
            for (name, shape), array in zip(info.inputs, arrays):
                if name in info.per_step:
                    buffers[name].reshape(-1, order="F")[:] = array[k].reshape(-1)
            status[k] = call()
            x_hist[k] = buffers["x"]
            P_hist[k] = buffers["P"].T

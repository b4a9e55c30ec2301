"""The gradient-descent MARG filter of paper 001 from Python: compiled filter and NumPy reference.

- :class:`MargFilter`: the compiled kernels of ``codegen/families/gradient_descent.py`` (full form
  (26)-(30) or simplified form (31); 6-axis ``"imu"`` or 9-axis ``"marg"``), one C call per sample
  (:meth:`MargFilter.step`) or one C call per recording (:meth:`MargFilter.run`, the generic C run
  loop with the real Δt of every sample). A thin :class:`~symkf.runtime.filters.Filter`: state
  x = q (scalar-last, unit), no covariance; the accelerometer and magnetometer samples are its
  measurement (a zero sample skips that correction).
- :func:`reference_run`: the same filter algebra in NumPy, calling the model's CasADi functions
  (gyro rate (7), gradient Jᵀf (13), earth-field reference): the readable oracle.

Recordings and the BROAD metric are experiment code: ``symkf.scenarios.marg.data`` / ``.metric``.
"""
from __future__ import annotations

import casadi as ca
import numpy as np

from symkf.codegen.families.gradient_descent import FORMS, MODES, ZERO_NORM, marg_functions
from symkf.models.marg import ALPHA_DEFAULT, BETA_MADGWICK
from . import contract
from .backends import SymkfError
from .filters import Filter, RunResult

#: Largest accepted deviation of an initial quaternion's norm from 1.
UNIT_TOLERANCE = 1e-6


class MargFilter(Filter):
    """Gradient-descent orientation filter (paper 001) over the compiled ``marg`` kernels.

    Args:
        compiled: ``symkf.runtime.load("marg")``.
        form: "simple" (eq (31), gain beta) or "full" (eqs (26)-(30), alpha and beta).
        mode: "marg" (9-axis: gyro, accelerometer, magnetometer) or "imu" (6-axis).
        beta: rad/s, eq (30)-(31).  alpha: eq (28), > 1 (full form only).
        q0: initial unit quaternion (scalar-last, sensor -> north-west-up); default identity,
            or call :meth:`initialize` with the first sample.

    ``q`` is the estimate (read-only view of the buffer the C code writes). A failed step
    raises :class:`SymkfError` and leaves ``q`` unchanged. NaN policy as every filter:
    ``nan="raise"`` (default) or ``nan="mask"`` (a non-finite acc or mag sample is skipped).
    """

    def __init__(self, compiled, form: str = "simple", mode: str = "marg", beta: float = BETA_MADGWICK,
                 alpha: float = ALPHA_DEFAULT, q0=None):
        if form not in FORMS or mode not in MODES:
            raise ValueError(f"form must be one of {FORMS} and mode one of {MODES}, got {form!r}, {mode!r}")
        q0 = np.array([0.0, 0.0, 0.0, 1.0]) if q0 is None else _unit("q0", q0)
        self.form, self.mode = form, mode
        self.kernel = f"gd_{form}_{mode}"
        super().__init__(compiled, self.kernel, q0, p=[_beta(beta), _alpha(alpha)])
        self._initial = self._backend.bind(f"gd_initial_{mode}", {**self._buffers, **self.measurements[mode]})

    # -------------------------------------------------------------- parameters and state
    @property
    def beta(self) -> float:
        return float(self._buffers["p"][0])

    @beta.setter
    def beta(self, value: float) -> None:
        self._buffers["p"][0] = _beta(value)

    @property
    def alpha(self) -> float:
        return float(self._buffers["p"][1])

    @alpha.setter
    def alpha(self, value: float) -> None:
        self._buffers["p"][1] = _alpha(value)

    @property
    def q(self) -> np.ndarray:
        return self.x

    @q.setter
    def q(self, value) -> None:
        self.x = _unit("q", value)

    # -------------------------------------------------------------- one sample
    def _samples(self, acc, mag) -> dict:
        if self.mode == "marg":
            return {"acc": acc, "mag": np.zeros(3) if mag is None else mag}
        return {"acc": acc, "mag": mag}

    def _mask_nonfinite(self, values: dict, buffers: dict) -> dict:
        """nan="mask": a non-finite accelerometer or magnetometer sample is skipped (zeroed)."""
        return {k: v if np.isfinite(v).all() else np.zeros_like(v) for k, v in values.items()}

    def initialize(self, acc, mag=None) -> np.ndarray:
        """Initial orientation from one sample (TRIAD; 6-axis: heading from a sensor axis)."""
        values = self._measurement_values(self.mode, self._samples(acc, mag), "raise")
        self._write_measurement(self.mode, values)
        code = self._initial()
        if code:
            raise SymkfError(f"gd_initial_{self.mode}", code, "acc and mag must be finite, non-zero and not parallel")
        return self.q

    def step(self, dt: float, gyro, acc, mag=None, nan: str = "raise") -> np.ndarray:
        """One sample: gyro (rad/s), acc, mag (any units; zero vector = skip that correction)."""
        gyro = contract.finite_array("gyro", gyro, (3,))
        self._step(self.mode, None, dt, self._samples(acc, mag), gyro, nan)
        return self.q

    # -------------------------------------------------------------- whole recordings
    def run(self, dt, gyro, acc, mag=None, nan: str = "raise") -> RunResult:
        """Filter N samples in one compiled call (per-sample dt, the first may be 0); q ends at
        the last sample. ``result.q`` holds the estimate after every sample."""
        dt = np.asarray(dt, dtype=float).ravel() if not isinstance(dt, str) else contract.real("dt", dt)
        n = dt.size
        if not (np.isfinite(dt).all() and np.all(dt[1:] > 0) and np.all(dt[:1] >= 0)):
            raise ValueError("dt: every step must be finite and > 0 (the first may be 0)")
        gyro = contract.finite_array("gyro", gyro, (n, 3))
        samples = self._samples(acc, np.zeros((n, 3)) if mag is None and self.mode == "marg" else mag)
        per_step = {"dt": dt, **self._run_series(self.mode, n, samples, gyro, nan)}
        return self._run(self.mode, per_step, n)

    def _run_nan_policy(self, series: dict, buffers: dict, nan: str) -> dict:
        for key in ("acc", "mag"):
            if key in series:
                bad = ~np.isfinite(series[key]).all(axis=1)
                if bad.any() and nan == "raise":
                    raise ValueError(f"{key}: NaN/Inf at samples {np.flatnonzero(bad)[:10].tolist()}; "
                                     "pass nan='mask' to skip them")
                series[key] = np.where(bad[:, None], 0.0, series[key])
        return series


def _unit(name: str, value) -> np.ndarray:
    q = contract.finite_array(name, value, (4,))
    norm = np.linalg.norm(q)
    if abs(norm - 1) > UNIT_TOLERANCE:
        raise ValueError(f"{name}: expected a finite unit quaternion [x, y, z, w], got norm {norm}")
    return q


def _beta(value) -> float:
    value = contract.real("beta", value)
    if value < 0:
        raise ValueError(f"beta: expected a finite number >= 0, got {value}")
    return value


def _alpha(value) -> float:
    value = contract.real("alpha", value)
    if value <= 1:
        raise ValueError(f"alpha: eq (28) needs alpha > 1, got {value}")
    return value


#: Older name of the run result (``run.q``, ``run.status``).
MargRun = RunResult


# ---------------------------------------------------------------------- NumPy reference
def _call(function: ca.Function, *args) -> np.ndarray:
    return np.asarray(function(*args)).ravel()


def _unit_or_zero(v: np.ndarray) -> tuple[np.ndarray, bool]:
    largest = np.max(np.abs(v))
    scaled = v / largest if largest > 0 else v
    norm = np.linalg.norm(scaled)
    return (scaled / norm, True) if largest * norm > ZERO_NORM else (np.zeros(3), False)


def reference_direction(q: np.ndarray, acc: np.ndarray, mag: np.ndarray | None) -> np.ndarray:
    """Eq (27) normalised, in NumPy around the model's CasADi gradients; zero when not correctable."""
    fns = marg_functions()
    a, acc_ok = _unit_or_zero(acc)
    m, mag_ok = _unit_or_zero(mag) if mag is not None else (np.zeros(3), False)
    if mag_ok:
        b = _call(fns["earth_field_reference"], q, m)
    if acc_ok and mag_ok:
        grad = _call(fns["gradient_stacked"], q, a, b, m)
    elif acc_ok:
        grad = _call(fns["gradient_gravity"], q, a)
    elif mag_ok:
        grad = _call(fns["gradient_earth_field"], q, b, m)
    else:
        return np.zeros(4)
    norm = np.linalg.norm(grad)
    return grad / norm if norm > ZERO_NORM else np.zeros(4)


def reference_step(form: str, q: np.ndarray, dt: float, gyro, acc, mag, beta: float, alpha: float) -> np.ndarray:
    """One step of (26)-(30) or (31) in NumPy (the model's equations evaluated by CasADi)."""
    q_dot = _call(marg_functions()["quaternion_rate"], q, gyro)        # (7)-(8)
    direction = reference_direction(q, np.asarray(acc, float), None if mag is None else np.asarray(mag, float))
    if form == "simple":
        q_est = q + (q_dot - beta * direction) * dt                    # (31)
    else:
        rate_nabla = alpha * np.linalg.norm(q_dot)                     # μ_t/Δt (28)
        corrected = bool(direction.any()) and rate_nabla + beta > 0
        gamma = beta / (rate_nabla + beta) if corrected else 0.0       # (30)
        q_est = gamma * (q - rate_nabla * dt * direction) + (1 - gamma) * (q + q_dot * dt)   # (26), (9), (29)
    return q_est / np.linalg.norm(q_est)


def reference_run(form: str, mode: str, q0, dt, gyro, acc, mag=None, beta: float = BETA_MADGWICK,
                  alpha: float = ALPHA_DEFAULT) -> np.ndarray:
    """The NumPy reference over N samples: (N, 4) estimates, the same contract as :meth:`MargFilter.run`."""
    q = np.asarray(q0, dtype=float).copy()
    out = np.zeros((len(dt), 4))
    for k in range(len(dt)):
        q = reference_step(form, q, dt[k], gyro[k], acc[k], mag[k] if mode == "marg" else None, beta, alpha)
        out[k] = q
    return out


def reference_initial(acc, mag) -> np.ndarray:
    """Initial orientation (TRIAD, 9-axis) via the model's CasADi function."""
    return _call(marg_functions()["initial_orientation"], acc, mag)


__all__ = ["MargFilter", "MargRun", "reference_initial", "reference_run", "reference_step"]

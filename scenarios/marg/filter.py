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

import numpy as np

from symkf.codegen.families.gradient_descent import FORMS, MODES
from symkf.models.marg import ALPHA_DEFAULT, BETA_MADGWICK
from symkf.runtime import contract
from symkf.runtime.backends import SymkfError
from symkf.runtime.filters import Filter, RunResult
from symkf.runtime.reference.gradient_descent import ReferenceMarg, reference_initial, reference_run, reference_step  # noqa: F401

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

    _BOUND = Filter._BOUND | {"_initial"}      # bound by _bind below: a copy binds its own

    def _bind(self) -> None:
        super()._bind()
        self._initial = self._backend.bind(f"gd_initial_{self.mode}", self._measurement_buffers(self.mode))

    def _make_fast_paths(self) -> None:
        """step(dt, gyro, acc, mag) in C: gyro required, a missing 9-axis magnetometer sample is zeros."""
        super()._make_fast_paths()
        self._fast_sample = self._fast_step(self.mode, ("acc", "mag", "u"))
        if self._scaling is None:                        # step returns the state view: self.x
            self._install_step(MargFilter.step, self._fast_sample, (None, "dt", "acc", "mag", "gyro"),
                               result=self._views["x"])

    #: Fast path of :meth:`step`: gyro (``u``) is required; an omitted 9-axis ``mag`` is a zero sample.
    FAST_NONE = {"mag": "zeros", "u": "decline"}

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
        fast = self._fast_sample
        if fast is not None and nan == "raise" and fast(None, dt, acc, mag, gyro) is not None:
            return self.x                       # (None: not a plain call, the Python path decides)
        gyro = contract.finite_array("gyro", gyro, (3,))
        self._step(self.mode, None, dt, self._samples(acc, mag), gyro, nan)
        return self.q

    # -------------------------------------------------------------- whole recordings
    def run(self, dt, gyro, acc, mag=None, nan: str = "raise") -> RunResult:
        """Filter N samples in one compiled call (per-sample dt, the first may be 0); q ends at
        the last sample. ``result.q`` holds the estimate after every sample."""
        dt = contract.as_array("dt", dt, np.shape(dt)).ravel()
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


__all__ = ["MargFilter", "MargRun", "ReferenceMarg", "reference_initial", "reference_run", "reference_step"]

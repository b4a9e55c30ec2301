"""The gradient-descent MARG filter of paper 001 from Python: compiled filter, NumPy reference, data, metric.

- :class:`MargFilter`: the compiled kernels of ``codegen/families/marg.py`` (full form (26)-(30) or
  simplified form (31); 6-axis ``"imu"`` or 9-axis ``"marg"``), one C call per sample
  (:meth:`MargFilter.step`) or one C call per recording (:meth:`MargFilter.run`, the generic C run
  loop with the real Δt of every sample).
- :func:`reference_run`: the same filter algebra in NumPy, calling the model's CasADi functions
  (gyro rate (7), gradient Jᵀf (13), earth-field reference): the readable oracle.
- :func:`load_recording`: BROAD ``.mat`` trials (Laidig et al. 2021, CC BY 4.0; optical reference)
  and the x-io Fusion CSV (MIT; no reference), as :class:`Recording`.
- :func:`broad_errors`: the BROAD error metric as ``../shared/data/README.md`` defines it:
  ``q_err = q_est ⊗ q_ref⁻¹`` (Hamilton), total ``2 acos|w|``, heading ``2 atan|z/w|``,
  inclination ``2 acos sqrt(w² + z²)``, RMSE over ``movement == 1`` with a finite reference, deg.
  The filter's earth frame is x = magnetic north, y = west, z = up; it is rotated into ENU by a
  left multiplication with a +90° rotation about z before the comparison.

Quaternions are scalar-last ``[x, y, z, w]`` everywhere in the project; BROAD's scalar-first
``opt_quat`` is converted on loading.
"""
from __future__ import annotations

import csv
import os
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import casadi as ca
import numpy as np

from symkf.codegen.families.gradient_descent import FORMS, MODES, ZERO_NORM, marg_functions
from symkf.models import quaternion as quat
from symkf.models.marg import ALPHA_DEFAULT, BETA_MADGWICK
from .backends import SymkfError
from .filters import as_array, read_only

#: +90° about z: left-multiplying a north-west-up orientation by it gives the east-north-up one.
NWU_TO_ENU = np.array([0.0, 0.0, np.sqrt(0.5), np.sqrt(0.5)])


def data_dir() -> Path:
    """``$SYMKF_DATA_DIR``, else ``../shared/data`` beside a source checkout, else ``./data``."""
    env = os.environ.get("SYMKF_DATA_DIR")
    if env:
        return Path(env)
    beside_checkout = Path(__file__).resolve().parents[2] / "shared" / "data"
    return beside_checkout if beside_checkout.is_dir() else Path("data")


# ---------------------------------------------------------------------- recordings
@dataclass
class Recording:
    """One recording, arrays per sample; ``reference``/``movement`` are None without ground truth.

    Attributes:
        time: (N,) s.  dt: (N,) s, ``dt[k] = time[k] - time[k-1]``, ``dt[0] = 0``.
        gyro: (N, 3) rad/s.  acc: (N, 3) (any unit; only its direction is used).
        mag: (N, 3) (any unit).  reference: (N, 4) scalar-last, sensor -> ENU, NaN where missing.
        movement: (N,) bool, the benchmark's movement phases.
    """

    name: str
    time: np.ndarray
    gyro: np.ndarray
    acc: np.ndarray
    mag: np.ndarray
    reference: np.ndarray | None = None
    movement: np.ndarray | None = None
    source: str = ""

    @property
    def dt(self) -> np.ndarray:
        return np.diff(self.time, prepend=self.time[:1])

    def __len__(self) -> int:
        return self.time.size

    def head(self, n: int) -> "Recording":
        """The first ``n`` samples (for quick tests)."""
        cut = slice(0, n)
        return Recording(self.name, self.time[cut], self.gyro[cut], self.acc[cut], self.mag[cut],
                         None if self.reference is None else self.reference[cut],
                         None if self.movement is None else self.movement[cut], self.source)


def load_broad(path: str | Path) -> Recording:
    """A BROAD trial (MATLAB v5 .mat): 285.714 Hz IMU, optical reference quaternion (ENU, scalar-first)."""
    from scipy.io import loadmat
    path = Path(path)
    data = loadmat(path)
    rate = float(np.squeeze(data["sampling_rate"]))
    n = data["imu_gyr"].shape[0]
    opt = np.asarray(data["opt_quat"], dtype=float)
    return Recording(path.stem, np.arange(n) / rate, np.asarray(data["imu_gyr"], float),
                     np.asarray(data["imu_acc"], float), np.asarray(data["imu_mag"], float),
                     opt[:, [1, 2, 3, 0]], np.asarray(data["movement"]).ravel() == 1,
                     "BROAD (Laidig et al. 2021, doi:10.3390/data6070072), CC BY 4.0")


def load_xio_csv(path: str | Path) -> Recording:
    """The x-io Fusion example CSV: time (s), gyro (deg/s), accelerometer (g), magnetometer (µT)."""
    path = Path(path)
    with open(path, newline="") as handle:
        reader = csv.reader(handle)
        header = next(reader)
        rows = np.array([[float(v) for v in row] for row in reader if row])
    if rows.ndim != 2 or rows.shape[1] != 10:
        raise ValueError(f"{path}: expected 10 columns (time, gyro xyz, acc xyz, mag xyz), got header {header}")
    return Recording(path.stem, rows[:, 0], np.deg2rad(rows[:, 1:4]), rows[:, 4:7], rows[:, 7:10],
                     source="x-io Technologies Fusion example data, MIT")


def load_recording(path: str | Path) -> Recording:
    """A BROAD ``.mat`` or an x-io ``.csv`` by file suffix."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such recording")
    if path.suffix == ".mat":
        return load_broad(path)
    if path.suffix == ".csv":
        return load_xio_csv(path)
    raise ValueError(f"{path}: expected a BROAD .mat or an x-io .csv file")


# ---------------------------------------------------------------------- compiled filter
@dataclass
class MargRun:
    """A whole run: the unit quaternion after every sample (N, 4) and each step's status code."""

    q: np.ndarray
    status: np.ndarray

    @property
    def failed_steps(self) -> np.ndarray:
        return np.flatnonzero(self.status)


def _series(name: str, value, n: int, width: int) -> np.ndarray:
    array = np.ascontiguousarray(value, dtype=float)
    expected = (n,) if width == 1 else (n, width)
    if array.shape != expected:
        raise ValueError(f"{name}: expected shape {expected}, got {array.shape}")
    return array


class MargFilter:
    """Gradient-descent orientation filter (paper 001) over the compiled ``marg`` kernels.

    Args:
        compiled: ``symkf.runtime.load("marg")``.
        form: "simple" (eq (31), gain beta) or "full" (eqs (26)-(30), alpha and beta).
        mode: "marg" (9-axis: gyro, accelerometer, magnetometer) or "imu" (6-axis).
        beta: rad/s, eq (30)-(31).  alpha: eq (28), > 1 (full form only).
        q0: initial unit quaternion (scalar-last, sensor -> north-west-up); default identity,
            or call :meth:`initialize` with the first sample.

    ``q`` is the estimate (read-only view of the buffer the C code writes). A failed step
    raises :class:`SymkfError` and leaves ``q`` unchanged.
    """

    def __init__(self, compiled, form: str = "simple", mode: str = "marg", beta: float = BETA_MADGWICK,
                 alpha: float = ALPHA_DEFAULT, q0=None):
        if form not in FORMS or mode not in MODES:
            raise ValueError(f"form must be one of {FORMS} and mode one of {MODES}, got {form!r}, {mode!r}")
        self.form, self.mode = form, mode
        self.kernel = f"gd_{form}_{mode}"
        self._backend = compiled.backend
        self._buffers = {"x": np.array([0.0, 0.0, 0.0, 1.0]), "dt": np.zeros(1), "u": np.zeros(3),
                         "acc": np.zeros(3), "mag": np.zeros(3), "p": np.zeros(2)}
        self.beta, self.alpha = beta, alpha
        if q0 is not None:
            self.q = q0
        self._step = self._backend.bind(self.kernel, self._buffers)
        self._initial = self._backend.bind(f"gd_initial_{mode}", self._buffers)

    # -------------------------------------------------------------- parameters and state
    @property
    def beta(self) -> float:
        return float(self._buffers["p"][0])

    @beta.setter
    def beta(self, value: float) -> None:
        if not np.isfinite(value) or value < 0:
            raise ValueError(f"beta: expected a finite number >= 0, got {value}")
        self._buffers["p"][0] = value

    @property
    def alpha(self) -> float:
        return float(self._buffers["p"][1])

    @alpha.setter
    def alpha(self, value: float) -> None:
        if not np.isfinite(value) or value <= 1:
            raise ValueError(f"alpha: eq (28) needs alpha > 1, got {value}")
        self._buffers["p"][1] = value

    @property
    def q(self) -> np.ndarray:
        return read_only(self._buffers["x"])

    @q.setter
    def q(self, value) -> None:
        value = as_array("q", value, (4,))
        norm = np.linalg.norm(value)
        if not np.isfinite(value).all() or abs(norm - 1) > 1e-6:
            raise ValueError(f"q: expected a finite unit quaternion [x, y, z, w], got norm {norm}")
        self._buffers["x"][:] = value

    # -------------------------------------------------------------- one sample
    def _load_sample(self, acc, mag) -> None:
        acc = as_array("acc", acc, (3,))
        mag = np.zeros(3) if mag is None else as_array("mag", mag, (3,))
        self._buffers["acc"][:], self._buffers["mag"][:] = acc, mag

    def initialize(self, acc, mag=None) -> np.ndarray:
        """Initial orientation from one sample (TRIAD; 6-axis: heading from a sensor axis)."""
        saved = self._buffers["x"].copy()
        self._load_sample(acc, mag)
        code = self._initial()
        if code:
            self._buffers["x"][:] = saved
            raise SymkfError(f"gd_initial_{self.mode}", code, "acc and mag must be non-zero and not parallel")
        return self.q

    def step(self, dt: float, gyro, acc, mag=None) -> np.ndarray:
        """One sample: gyro (rad/s), acc, mag (any units; zero vector = skip that correction)."""
        self._buffers["u"][:] = as_array("gyro", gyro, (3,))
        self._load_sample(acc, mag)
        self._buffers["dt"][0] = dt
        code = self._step()
        if code:
            raise SymkfError(self.kernel, code, "dt and beta must be >= 0 and the samples finite")
        return self.q

    # -------------------------------------------------------------- whole recordings
    def run(self, dt, gyro, acc, mag=None) -> MargRun:
        """Filter N samples in one compiled call (per-sample dt); q ends at the last sample.

        A failed step (status != 0, e.g. a NaN sample) keeps the previous estimate and is
        recorded in ``status``; the other steps go on.
        """
        dt = np.asarray(dt, dtype=float).ravel()
        n = dt.size
        per_step = {"dt": dt, "u": _series("gyro", gyro, n, 3), "acc": _series("acc", acc, n, 3)}
        if self.mode == "marg":
            per_step["mag"] = np.zeros((n, 3)) if mag is None else _series("mag", mag, n, 3)
        q_hist, status = np.zeros((n, 4)), np.zeros(n, dtype=np.intc)
        run = self._backend.run_function(self.kernel)
        info = self._backend.kernels[self.kernel]
        arrays = [per_step[name] if name in per_step else self._buffers[name] for name, _ in info.inputs]
        if run is not None:
            run(n, *[a.ctypes.data for a in arrays], q_hist.ctypes.data, status.ctypes.data)
        else:       # CasADi-VM backend: the same kernel, one call per sample
            self._run_in_python(per_step, q_hist, status)
        if n:
            self._buffers["x"][:] = q_hist[-1]
        return MargRun(q_hist, status)

    def _run_in_python(self, per_step: dict, q_hist: np.ndarray, status: np.ndarray) -> None:
        for k in range(status.size):
            for name, series in per_step.items():
                self._buffers[name][:] = series[k]
            status[k] = self._step()
            q_hist[k] = self._buffers["x"]

    def run_recording(self, recording: Recording, initialize: bool = True) -> MargRun:
        """Initialise from the first sample (if asked) and filter the whole recording."""
        mag = recording.mag if self.mode == "marg" else None
        if initialize:
            self.initialize(recording.acc[0], None if mag is None else mag[0])
        return self.run(recording.dt, recording.gyro, recording.acc, mag)


# ---------------------------------------------------------------------- NumPy reference
def _call(function: ca.Function, *args) -> np.ndarray:
    return np.asarray(function(*args)).ravel()


def _unit_or_zero(v: np.ndarray) -> tuple[np.ndarray, bool]:
    norm = np.linalg.norm(v)
    return (v / norm, True) if norm > ZERO_NORM else (np.zeros(3), False)


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


# ---------------------------------------------------------------------- Euler angles, metric
@lru_cache(maxsize=None)
def _mapped(name: str, n: int) -> ca.Function:
    if name == "hamilton":
        p, q = ca.SX.sym("p", 4), ca.SX.sym("q", 4)
        return ca.Function("hamilton", [p, q], [quat.hamilton(p, q)]).map(n)
    return marg_functions()[name].map(n)


def euler_angles(q: np.ndarray) -> np.ndarray:
    """Eq (5) (on q*, i.e. the sensor's yaw psi, pitch theta, roll phi) for (N, 4) quaternions -> (N, 3) rad."""
    q = np.atleast_2d(q)
    return np.asarray(_mapped("euler_angles", q.shape[0])(q.T)).T


def to_enu(q_nwu: np.ndarray) -> np.ndarray:
    """Estimates in the filter's north-west-up earth frame -> ENU (left-multiply by +90° about z)."""
    q_nwu = np.atleast_2d(q_nwu)
    rot = np.repeat(NWU_TO_ENU[:, None], q_nwu.shape[0], axis=1)
    return np.asarray(_mapped("hamilton", q_nwu.shape[0])(rot, q_nwu.T)).T


def from_enu(q_enu: np.ndarray) -> np.ndarray:
    """The inverse of :func:`to_enu` (e.g. the optical reference in the filter's frame); NaN rows stay NaN."""
    q_enu = np.atleast_2d(q_enu)
    rot = np.repeat(quat_conjugate(NWU_TO_ENU)[:, None], q_enu.shape[0], axis=1)
    return np.asarray(_mapped("hamilton", q_enu.shape[0])(rot, q_enu.T)).T


def quat_conjugate(q: np.ndarray) -> np.ndarray:
    """Conjugate of scalar-last quaternion(s)."""
    return q * np.array([-1.0, -1.0, -1.0, 1.0])


def error_quaternions(q_est_enu: np.ndarray, q_ref_enu: np.ndarray) -> np.ndarray:
    """BROAD's earth-frame error q_err = q_est ⊗ q_ref⁻¹ (both normalised), (N, 4) scalar-last."""
    est = q_est_enu / np.linalg.norm(q_est_enu, axis=1, keepdims=True)
    ref = q_ref_enu / np.linalg.norm(q_ref_enu, axis=1, keepdims=True)
    return np.asarray(_mapped("hamilton", est.shape[0])(est.T, quat_conjugate(ref).T)).T


def error_rotation_vectors(q_est_enu: np.ndarray, q_ref_enu: np.ndarray) -> np.ndarray:
    """(N, 3) rotation vectors (rad, earth frame) of :func:`error_quaternions`, the short way round."""
    err = error_quaternions(q_est_enu, q_ref_enu)
    err = err * np.where(err[:, 3:] < 0, -1.0, 1.0)
    vec_norm = np.linalg.norm(err[:, :3], axis=1, keepdims=True)
    angle = 2 * np.arctan2(vec_norm, err[:, 3:])
    return err[:, :3] * np.where(vec_norm > 0, angle / np.where(vec_norm > 0, vec_norm, 1), 2.0)


def broad_error_angles(q_est_enu: np.ndarray, q_ref_enu: np.ndarray) -> np.ndarray:
    """(N, 3) total, heading, inclination error angles (rad) of BROAD's metric (NaN where no reference)."""
    err = error_quaternions(q_est_enu, q_ref_enu)
    w, z = np.abs(err[:, 3]), np.abs(err[:, 2])
    total = 2 * np.arccos(np.clip(w, 0, 1))
    heading = 2 * np.arctan2(z, w)
    inclination = 2 * np.arccos(np.clip(np.sqrt(w**2 + z**2), 0, 1))
    return np.column_stack([total, heading, inclination])


def broad_errors(q_est_nwu: np.ndarray, recording: Recording) -> dict[str, float]:
    """BROAD RMSE (deg) over movement phases with a finite reference: total, heading, inclination."""
    if recording.reference is None or recording.movement is None:
        raise ValueError(f"{recording.name}: no optical reference, the BROAD metric needs one")
    angles = broad_error_angles(to_enu(q_est_nwu), recording.reference)
    used = recording.movement & np.isfinite(recording.reference).all(axis=1)
    rmse = np.degrees(np.sqrt(np.mean(angles[used] ** 2, axis=0)))
    return {"total": float(rmse[0]), "heading": float(rmse[1]), "inclination": float(rmse[2]),
            "samples": int(used.sum())}


__all__ = ["MargFilter", "MargRun", "Recording", "broad_error_angles", "broad_errors", "data_dir", "error_quaternions",
           "error_rotation_vectors", "euler_angles",
           "from_enu", "load_broad", "load_recording", "load_xio_csv", "reference_initial", "reference_run",
           "reference_step", "to_enu"]

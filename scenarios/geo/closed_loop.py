"""Koreasat-3 closed loop (paper 003, Fig 3): truth, multi-rate sensors, estimator, 2 Hz PID.

One base tick of 1/8 s (the fastest sensor). At tick k (time t_k):

1. sensors sample the truth: sun sensor (psi) and gyros every tick (8 Hz), earth sensor
   (phi, theta) every 2nd tick (4 Hz), tachometers every 4th tick (2 Hz, our choice, see
   ``models/geo_satellite.py``); noise sigma of Table 5 when ``noise`` is on;
2. the estimator runs: either the continuous-discrete EKF (``cd_ekf``: predict from t_{k-1} with
   the wheel torques that were applied, then one masked update per sensor that sampled), or the
   paper's "No EKF" path: angles straight from the angle sensors (held between samples), rates by
   least squares from the working gyros (minimum-norm solution when they do not span 3 axes),
   and the controller's own integral of the measured angles (rectangle rule at 2 Hz);
3. every 4th tick (2 Hz) the PID law eq (5) computes new wheel torques, held (zero-order hold)
   until the next control tick;
4. the truth is integrated to t_{k+1} with the model's own RK4 (``truth_substeps`` per tick).

After the loop (``smooth``, on by default) the estimator's record is smoothed: the CD-EKF's RTS
smoother (the compiled ``cd_ekf_smooth_run``, or for "numpy-ekf" the NumPy reference
``cd_ekf_rts``) over each tick's filtered x, P and the torques that were applied. It is an
after-the-fact estimate only: the controller saw the filtered estimate at each tick, and the
smoother runs once the loop has ended, so it cannot feed the controller (a test checks that the
loop is bit-identical with and without it).

A failed gyro is an availability mask (its output is NaN, its mask 0): the same compiled update
runs in every case. ``symkf.runtime.reference.NumpyCDEKF`` is the plain NumPy reference of the
compiled filter.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np

from symkf.codegen.families.cd_ekf import reference_functions
from symkf.models import geo_satellite as geo
from symkf.models import get_model
from symkf.runtime import SymkfError, smooth
from symkf.runtime.reference import NumpyCDEKF
from symkf.runtime.reference.rts import cd_ekf_rts
from symkf.runtime.runs import RunResult

BASE_RATE_HZ = geo.GYRO_RATE_HZ
TICK = 1.0 / BASE_RATE_HZ
#: Sensor period in base ticks (4 Hz earth sensor, 8 Hz sun sensor and gyros, 2 Hz tachometers).
SENSOR_PERIOD_TICKS = {"sun_sensor": int(BASE_RATE_HZ / geo.SUN_SENSOR_RATE_HZ),
                       "earth_sensor": int(BASE_RATE_HZ / geo.EARTH_SENSOR_RATE_HZ),
                       "gyro": int(BASE_RATE_HZ / geo.GYRO_RATE_HZ),
                       "tacho": int(BASE_RATE_HZ / geo.TACHO_RATE_HZ)}
CONTROL_PERIOD_TICKS = int(BASE_RATE_HZ / geo.CONTROL_RATE_HZ)
INITIAL_TABLES = {"table4": geo.TABLE4, "table6": geo.TABLE6}


def gyro_indices(names) -> list[int]:
    """Gyro letters ("A".."D") -> row indices of eq (1); ValueError names an unknown one."""
    indices = []
    for name in names:
        if name not in geo.GYRO_NAMES:
            raise ValueError(f"failed_gyros: '{name}' is not one of {geo.GYRO_NAMES}")
        indices.append(geo.GYRO_NAMES.index(name))
    return indices


def working_geometry(failed) -> np.ndarray:
    """Rows of eq (1) for the gyros that still work."""
    keep = [i for i in range(4) if i not in gyro_indices(failed)]
    return geo.gyro_geometry()[keep]


def geometry_rank(failed) -> int:
    """Rank of the working gyros' geometry: 3 means omega is observable from them."""
    rows = working_geometry(failed)
    return int(np.linalg.matrix_rank(rows)) if rows.size else 0


@functools.lru_cache(maxsize=None)
def _rate_solver(failed: tuple[str, ...]) -> tuple[list[int], np.ndarray]:
    keep = [i for i in range(4) if i not in gyro_indices(failed)]
    rows = working_geometry(failed)
    return keep, (np.linalg.pinv(rows) if rows.size else np.zeros((3, 0)))


def least_squares_rates(gyro_output: np.ndarray, failed) -> np.ndarray:
    """Body rates from the working gyros: minimum-norm least squares (0 if none works)."""
    keep, solver = _rate_solver(tuple(failed))
    return solver @ gyro_output[keep]


# ---------------------------------------------------------------------- closed loop
@dataclass(frozen=True)
class LoopSettings:
    """One closed-loop run.

    Attributes:
        duration: simulated seconds.
        estimator: "ekf" (compiled cd_ekf), "numpy-ekf" (the NumPy reference) or "sensors"
            (the paper's "No EKF": sensor angles + least-squares gyro rates).
        bias: gyro biases of the initial-error table on (else 0).
        noise: sensor noise (Table 5 sigma) on.
        failed_gyros: letters of failed gyros, e.g. ("A", "C").
        initial: "table6" (section 4) or "table4" (section 3) initial errors of the truth; the
            filter starts from x = 0, so these are also the filter's initial errors.
        truth_substeps: RK4 steps of the truth per 1/8 s tick.
        smooth: also smooth the estimator's record once the loop has ended (EKF estimators).
    """

    duration: float = 1000.0
    estimator: str = "ekf"
    bias: bool = True
    noise: bool = True
    failed_gyros: tuple[str, ...] = ()
    initial: str = "table6"
    seed: int = 0
    truth_substeps: int = 4
    units: str = "paper"
    smooth: bool = True


@dataclass
class LoopResult:
    """Histories, one row per 1/8 s tick (time t_k, after the estimator ran at t_k)."""

    settings: LoopSettings
    t: np.ndarray
    truth: np.ndarray                   # (N, 17)
    estimate: np.ndarray                # (N, 17); NaN where the estimator has no such quantity
    sigma: np.ndarray                   # (N, 17) sqrt(diag P) (NaN without EKF)
    wheel_torque: np.ndarray            # (N, 4) commanded, held over the tick
    body_torque: np.ndarray             # (N, 3) eq (5)
    failures: list = field(default_factory=list)
    smoothed: np.ndarray | None = None          # (N, 17) the RTS estimate given the whole record
    smoothed_sigma: np.ndarray | None = None    # (N, 17) sqrt(diag P_smooth)
    smooth_status: np.ndarray | None = None     # (N,) 0 or the SYMKF_ERR_* code of a refused backward step

    @property
    def attitude_deg(self) -> np.ndarray:
        """True attitude angles (deg): the attitude error, the commanded attitude being 0."""
        return np.rad2deg(self.truth[:, geo.SLICES["angle"]])

    def estimation_error(self, block: str, smoothed: bool = False) -> np.ndarray:
        """Estimate minus truth of one state block, filtered (as the controller saw it) or smoothed."""
        s = geo.SLICES[block]
        if smoothed and self.smoothed is None:
            raise ValueError("estimation_error: this run has no smoothed estimate (no EKF, or smooth=False)")
        return (self.smoothed if smoothed else self.estimate)[:, s] - self.truth[:, s]


class ClosedLoop:
    """Truth + sensors + estimator + PID (see the module docstring); one object per run."""

    def __init__(self, settings: LoopSettings, compiled=None):
        self.settings = s = settings
        if s.estimator not in ("ekf", "numpy-ekf", "sensors"):
            raise ValueError(f"estimator: expected 'ekf', 'numpy-ekf' or 'sensors', got '{s.estimator}'")
        if s.initial not in INITIAL_TABLES:
            raise ValueError(f"initial: expected one of {sorted(INITIAL_TABLES)}, got '{s.initial}'")
        self.failed = tuple(s.failed_gyros)
        self.gyro_mask = np.ones(4)
        self.gyro_mask[gyro_indices(self.failed)] = 0.0
        self.compiled = compiled if compiled is not None else _load(s.units)
        self.model_sym = get_model("geo_satellite") if s.units == "paper" else geo.build(s.units)
        self.control_law = geo.control_law(s.units)
        self.sigma = {name: np.array(m["sigma"]) for name, m in self.compiled.model["measurements"].items()}
        self.rng = np.random.default_rng(s.seed)
        self._bind_truth()
        self.tuning = geo.filter_tuning(s.units)
        self.filter = self._make_filter()

    def _bind_truth(self) -> None:
        backend = self.compiled.backend
        self.buf = {"t": np.zeros(1), "dt": np.zeros(1), "x": np.zeros(17), "u": np.zeros(4), "p": np.zeros(0),
                    "q": np.zeros(0)}
        self.truth_step = backend.bind("fd", self.buf)
        self.sensor_buffers = {}
        self.sensor_calls = {}
        for name, meas in self.compiled.model["measurements"].items():
            buffers = {**self.buf, "z": np.zeros(len(meas["outputs"]))}
            self.sensor_buffers[name] = buffers
            self.sensor_calls[name] = backend.bind(f"h_{name}", buffers)

    def _make_filter(self):
        s, tune = self.settings, self.tuning
        x0 = np.zeros(17)
        if s.estimator == "ekf":
            return self.compiled.filter("cd_ekf", x0, tune["P0"], tune["Q"], R=tune["R"], gate="none")   # paper 003: no gate
        if s.estimator == "numpy-ekf":
            return NumpyCDEKF(self.model_sym, x0, tune["P0"], tune["Q"], tune["R"],
                              int(self.model_sym.codegen_defaults.get("rk4_substeps", 1)))
        return None

    # ------------------------------------------------------------------ pieces
    def sense(self, name: str, x: np.ndarray) -> np.ndarray:
        """Sensor ``name`` sampling the true state x (eq (1) for gyros), noise if on."""
        self.buf["x"][:] = x
        self._call(self.sensor_calls[name], f"h_{name}")
        z = self.sensor_buffers[name]["z"].copy()
        if self.settings.noise:
            z += self.sigma[name] * self.rng.standard_normal(z.size)
        return z

    def propagate_truth(self, t: float, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        n = self.settings.truth_substeps
        self.buf["u"][:] = u
        self.buf["x"][:] = x
        self.buf["dt"][0] = TICK / n
        for i in range(n):
            self.buf["t"][0] = t + i * TICK / n
            self._call(self.truth_step, "fd")
        return self.buf["x"].copy()

    @staticmethod
    def _call(call, what: str) -> None:
        code = call()
        if code:
            raise SymkfError(what, code)

    def command(self, integral, angle, rate) -> tuple[np.ndarray, np.ndarray]:
        """Eq (5) and the wheel distribution (model's control law)."""
        wheel, body = self.control_law(integral, angle, rate)
        return np.asarray(wheel).ravel(), np.asarray(body).ravel()

    # ------------------------------------------------------------------ run
    def run(self) -> LoopResult:
        s = self.settings
        n_ticks = int(round(s.duration / TICK)) + 1
        x = geo.initial_errors(INITIAL_TABLES[s.initial], s.units, bias=s.bias)
        hist = {k: np.full((n_ticks, w), np.nan) for k, w in
                (("truth", 17), ("estimate", 17), ("sigma", 17), ("wheel", 4), ("body", 3), ("applied", 4))}
        covariances = np.full((n_ticks, 17, 17), np.nan) if self.filter is not None else None
        u, body = np.zeros(4), np.zeros(3)
        sensed = {"angle": np.zeros(3), "integral": np.zeros(3), "rate": np.zeros(3), "momentum": np.zeros(4)}
        for k in range(n_ticks):
            t = k * TICK
            hist["applied"][k] = u                          # the torques held over [t_{k-1}, t_k]
            if self.filter is not None:
                estimate = self._filter_tick(k, t, x, u)
                covariances[k] = self.filter.P
                hist["sigma"][k] = np.sqrt(np.clip(np.diag(covariances[k]), 0, None))
            else:
                estimate = self._sensor_tick(k, x, sensed)
            if k % CONTROL_PERIOD_TICKS == 0:
                if self.filter is None:
                    sensed["integral"] += sensed["angle"] * (CONTROL_PERIOD_TICKS * TICK)
                    estimate[geo.SLICES["integral"]] = sensed["integral"]
                u, body = self.command(estimate[geo.SLICES["integral"]], estimate[geo.SLICES["angle"]],
                                       estimate[geo.SLICES["rate"]])
            hist["truth"][k], hist["estimate"][k], hist["wheel"][k], hist["body"][k] = x, estimate, u, body
            if not np.all(np.isfinite(x)) or np.max(np.abs(x[geo.SLICES["angle"]])) > np.pi / 2:
                hist = {key: value[:k + 1] for key, value in hist.items()}
                break                                       # diverged beyond the model's validity
            x = self.propagate_truth(t, x, u)
        n = hist["truth"].shape[0]
        result = LoopResult(s, np.arange(n) * TICK, hist["truth"], hist["estimate"], hist["sigma"],
                            hist["wheel"], hist["body"])
        if s.smooth and self.filter is not None:
            self._smooth(result, covariances[:n], hist["applied"])
        return result

    def _smooth(self, result: LoopResult, P: np.ndarray, applied: np.ndarray) -> None:
        """The RTS smoothing of the loop's record, after the loop (see the module docstring):
        step k predicted from t_{k-1} over one tick with the torques ``applied[k]``; tick 0 only
        updated. A refused backward step keeps its filtered row and its code (smooth_status)."""
        n = result.t.size
        t, dt = np.maximum(result.t - TICK, 0.0), np.where(np.arange(n) > 0, TICK, 0.0)
        if self.settings.estimator == "numpy-ekf":
            xs, Ps = cd_ekf_rts(self.filter, result.estimate, P, t, dt, applied)
            codes = np.zeros(n, dtype=int)
        else:
            record = RunResult(result.estimate, P, np.zeros(n, dtype=np.intc),
                               {"t": t, "dt": dt, "u": applied, "p": np.zeros(0), "Q": self.tuning["Q"]})
            smoothed = smooth(self.filter, record, errors="keep")
            xs, Ps, codes = smoothed.x_smooth, smoothed.P_smooth, smoothed.smooth_status
        result.smoothed, result.smooth_status = xs, codes
        result.smoothed_sigma = np.sqrt(np.clip(np.einsum("kii->ki", Ps), 0, None))

    def _filter_tick(self, k: int, t: float, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        ekf = self.filter
        if k > 0:
            ekf.predict(t - TICK, TICK, u=u)
        for name, period in SENSOR_PERIOD_TICKS.items():
            if k % period:
                continue
            z = self.sense(name, x)
            mask = self.gyro_mask if name == "gyro" else np.ones(z.size)
            z = np.where(mask > 0, z, np.nan)               # a failed gyro outputs nothing
            ekf.update(z, measurement=name, mask=mask, u=u)
        return np.array(ekf.x, dtype=float)

    def _sensor_tick(self, k: int, x: np.ndarray, sensed: dict) -> np.ndarray:
        estimate = np.full(17, np.nan)
        if k % SENSOR_PERIOD_TICKS["sun_sensor"] == 0:
            sensed["angle"][0] = self.sense("sun_sensor", x)[0]
        if k % SENSOR_PERIOD_TICKS["earth_sensor"] == 0:
            sensed["angle"][1:] = self.sense("earth_sensor", x)
        if k % SENSOR_PERIOD_TICKS["gyro"] == 0:
            sensed["rate"] = least_squares_rates(self.sense("gyro", x), self.failed)
        if k % SENSOR_PERIOD_TICKS["tacho"] == 0:
            sensed["momentum"] = self.sense("tacho", x)
        estimate[geo.SLICES["integral"]] = sensed["integral"]
        estimate[geo.SLICES["angle"]] = sensed["angle"]
        estimate[geo.SLICES["rate"]] = sensed["rate"]
        estimate[geo.SLICES["momentum"]] = sensed["momentum"]
        return estimate


_LOADED: dict[str, object] = {}


def _load(units: str = "paper"):
    """The compiled geo_satellite model (built on first use, cached per process)."""
    if units != "paper":
        raise ValueError("the compiled closed loop runs the paper-unit model; use units='paper'")
    if "paper" not in _LOADED:
        from symkf.runtime import load
        _LOADED["paper"] = load("geo_satellite")
    return _LOADED["paper"]


def simulate(settings: LoopSettings, compiled=None) -> LoopResult:
    """Run one closed loop (see :class:`ClosedLoop`)."""
    return ClosedLoop(settings, compiled).run()


def closed_loop_eigenvalues(failed=(), estimator: str = "sensors", units: str = "paper") -> np.ndarray:
    """Eigenvalues of the "No EKF" loop linearised about the commanded attitude (continuous PID).

    Rates enter the PID as the least-squares estimate pinv(G_w) G_w omega, so a direction the
    working gyros cannot see gets no rate damping. Only the (integral, angle, rate) block is
    returned: at omega = 0 wheel momenta and biases do not feed back. The 2 Hz zero-order hold
    is ignored (the loop's poles are below 0.1 rad/s, far under the 12.6 rad/s sampling rate).
    """
    if estimator != "sensors":
        raise ValueError("closed_loop_eigenvalues: only the sensor ('No EKF') loop is linearised here")
    model = get_model("geo_satellite") if units == "paper" else geo.build(units)
    functions = reference_functions(model)
    x0 = geo.initial_errors(geo.TABLE6, units, bias=False)
    x0[geo.SLICES["angle"]], x0[geo.SLICES["rate"]] = 0.0, 0.0
    A = np.asarray(functions["A"](0.0, x0, np.zeros(4), []))
    B = np.column_stack([np.asarray(functions["a"](0.0, x0, e, [])).ravel()
                         - np.asarray(functions["a"](0.0, x0, np.zeros(4), [])).ravel() for e in np.eye(4)])
    keep, solver = _rate_solver(tuple(failed))
    rate_map = solver @ geo.gyro_geometry()[keep] if keep else np.zeros((3, 3))
    law = geo.control_law(units)
    C = np.zeros((4, 17))
    for j in range(9):                      # the law is linear: its columns by unit inputs
        e = np.zeros(9)
        e[j] = 1.0
        rate = rate_map @ e[6:9]
        C[:, j] = np.asarray(law(e[0:3], e[3:6], rate)[0]).ravel()
    closed = (A + B @ C)[:9, :9]
    return np.linalg.eigvals(closed)

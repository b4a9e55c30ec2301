"""Attitude filters of paper 000 over the generated kernels, and their NumPy references.

:class:`AttitudeFilter` is a thin view of buffers bound once to the ``attitude`` kernels
(``kind`` = "mekf", "ukf" (the paper's separated-space UKF) or "aukf" (full augmented UKF));
:class:`ReferenceAttitudeFilter` is the same algebra written in NumPy (model equations evaluated
through the same CasADi Functions, the quaternion mean by ``numpy.linalg.eigh`` of N (36)).
Both follow codegen/families/attitude.py, which documents the equations.

Conventions: x = [q; b] with q scalar-last (paper 000), P the 6x6 covariance of [δp; δb],
δp the vector part of δq = q ⊗ q̂⁻¹ (half-angle units). Q: 6x6 PSD of [η_a; η_b]; R: 3x3
covariance of the star-tracker noise rotation vector η_s. Defaults: Table 1.

Bad input: shapes are checked (ValueError naming the argument); an initial quaternion is
normalised if its norm is within 1e-3 of 1 and rejected otherwise; a star-tracker quaternion
with NaN/Inf is rejected with ValueError (pass ``None`` to skip a missing measurement; in
:meth:`AttitudeFilter.run` a NaN row means "no measurement"); a star-tracker quaternion whose
norm is off 1 by more than 1e-3 is rejected by the kernel (SYMKF_ERR_DOMAIN), smaller deviations
are normalised. A failed step raises SymkfError and leaves x and P unchanged.
"""
from __future__ import annotations

import numpy as np

from symkf.codegen.families import quaternion_filters as family
from symkf.codegen.spec import STATUS_DOMAIN, STATUS_NONFINITE, STATUS_NOT_PD
from symkf.models import attitude as model
from . import contract
from .backends import SymkfError
from .contract import as_array, covariance, read_only
from .filters import Filter, RunResult

KINDS = ("mekf", "ukf", "aukf")
#: UKF scaling κ used unless given: keeps every weight positive (paper 000 leaves κ open).
DEFAULT_KAPPA = family.DEFAULT_KAPPA
#: Largest accepted deviation of an initial quaternion's norm from 1 (smaller ones are normalised).
NORM_TOLERANCE = family.MEASUREMENT_NORM_TOLERANCE


def unit_quaternion(name: str, value) -> np.ndarray:
    """``value`` as a unit quaternion (normalised); ValueError if not finite or |norm - 1| > 1e-3."""
    q = as_array(name, value, (4,))
    if not np.isfinite(q).all():
        raise ValueError(f"{name}: contains NaN or Inf")
    norm = np.linalg.norm(q)
    if abs(norm - 1) > NORM_TOLERANCE:
        raise ValueError(f"{name}: norm {norm:.6g} is not 1 (tolerance {NORM_TOLERANCE}); not an attitude quaternion")
    return q / norm


def _initial_state(q0, b0, P0) -> tuple[np.ndarray, np.ndarray]:
    x = np.concatenate([unit_quaternion("q0", q0), as_array("b0", b0, (3,))])
    if not np.isfinite(x).all():
        raise ValueError("b0: contains NaN or Inf")
    return x, covariance("P0", P0, 6)


def _measurement(q_s) -> np.ndarray:
    z = as_array("q_s", q_s, (4,))
    if not np.isfinite(z).all():
        raise ValueError("q_s: star-tracker quaternion contains NaN or Inf; pass None to skip the update")
    return z



class AttitudeFilter(Filter):
    """MEKF, the paper's UKF or the augmented UKF of a compiled ``attitude`` model (a thin
    :class:`~symkf.runtime.filters.Filter`: the paper's argument names over the generic one).

    Args:
        compiled: ``symkf.runtime.load("attitude")``.
        kind: "mekf", "ukf" or "aukf".
        q0, b0, P0: initial quaternion, gyro bias (rad/s) and 6x6 error covariance.
        Q, R: noise (defaults: Table 1 via models/attitude.py).
        kappa: UKF scaling (ignored by the MEKF).

    Attributes (read-only views): x, q, b, P; y and S of the last update (innovation δp_s, P^yy).
    """

    MEASUREMENT = "star_tracker"

    def __init__(self, compiled, kind: str, q0, b0, P0, Q=None, R=None, kappa: float = DEFAULT_KAPPA):
        if kind not in KINDS:
            raise ValueError(f"kind: expected one of {KINDS}, got {kind!r}")
        x, P = _initial_state(q0, b0, P0)
        Q = model.process_noise_psd() if Q is None else Q
        R = {self.MEASUREMENT: model.star_tracker_covariance() if R is None else R}
        options = {} if kind == "mekf" else {"kappa": kappa}
        super().__init__(compiled, kind, x, P, Q, R=R, **options)
        self.kind = kind

    y = property(lambda self: read_only(self.measurements["star_tracker"]["y"]),
                 doc="Innovation δp_s of the last update (eq 50).")
    S = property(lambda self: read_only(self.measurements["star_tracker"]["S"]),
                 doc="Innovation covariance P^yy of the last update.")
    q = property(lambda self: self.x[0:4], doc="Attitude quaternion estimate (scalar-last).")
    b = property(lambda self: self.x[4:7], doc="Gyro bias estimate, rad/s.")

    def body_rate(self, omega_g) -> np.ndarray:
        """Eq (53): ω̂ = ω_g + b̂."""
        return contract.finite_array("omega_g", omega_g, (3,)) + self.b

    def predict(self, omega_g, dt: float) -> None:
        """Propagate over dt with gyro output omega_g (rad/s)."""
        super().predict(self.t, dt, u=contract.finite_array("omega_g", omega_g, (3,)))

    def update(self, q_s, nan: str = "raise") -> int:
        """Star-tracker update with quaternion q_s (MEKF and separated UKF)."""
        if not self.spec.update:
            raise ValueError("update: the augmented UKF updates only inside step(omega_g, dt, q_s)")
        return super().update(q_s, nan=nan)

    def step(self, omega_g, dt: float, q_s=None, nan: str = "raise") -> int:
        """Propagate over dt, then update with q_s if it is not None — one compiled call."""
        if q_s is None:
            self.predict(omega_g, dt)
            return 0
        omega_g = contract.finite_array("omega_g", omega_g, (3,))
        return self._step(self.MEASUREMENT, self.t, dt, {"z": q_s, "mask": None}, omega_g, nan)

    def run(self, omega_g, dt, q_s) -> RunResult:
        """All steps in one compiled call (the C run loop). Step k propagates over dt[k] (> 0)
        with omega_g[k] and updates with q_s[k] unless that row has NaN (no measurement)."""
        omega_g = np.asarray(omega_g, dtype=float) if not isinstance(omega_g, str) else omega_g
        n_steps = omega_g.shape[0] if isinstance(omega_g, np.ndarray) and omega_g.ndim == 2 else -1
        omega_g = contract.finite_array("omega_g", omega_g, (max(n_steps, 0), 3))
        dt = np.broadcast_to(contract.as_array("dt", dt, np.shape(dt)), (n_steps,))
        if not (np.isfinite(dt).all() and np.all(dt > 0)):
            raise ValueError("dt: every step must be finite and > 0")
        per_step = {"t": self.t + np.concatenate([[0.0], np.cumsum(dt)[:-1]]), "dt": dt}
        per_step.update(self._run_series(self.MEASUREMENT, n_steps, {"z": q_s, "mask": None}, omega_g, "mask"))
        result = self._run(self.MEASUREMENT, per_step, n_steps)
        return result


# ---------------------------------------------------------------------- NumPy reference
class _Functions:
    """The CasADi Functions the reference evaluates (built once per process)."""

    _instance = None

    @classmethod
    def get(cls) -> "_Functions":
        if cls._instance is None:
            cls._instance = cls()
        return cls._instance

    def __init__(self):
        fns = family.AttitudeFunctions("attitude_reference")
        self.fns = fns
        self.transition, self.measurement = family.error_state_jacobians(fns)

    def perturb(self, delta_x, q, b):
        q_i, b_i, ok = self.fns.perturb(delta_x, q, b)
        return np.asarray(q_i).ravel(), np.asarray(b_i).ravel(), bool(ok)

    def propagate(self, q, b, omega_g, eta_a, eta_b, dt):
        q_next, b_next = self.fns.propagate(q, b, omega_g, eta_a, eta_b, dt)
        return np.asarray(q_next).ravel(), np.asarray(b_next).ravel()

    def star_tracker(self, q, eta_s) -> np.ndarray:
        return np.asarray(self.fns.star_tracker(q, eta_s)).ravel()

    def error_vector(self, q, q_ref) -> np.ndarray:
        return np.asarray(self.fns.error_vector(q, q_ref)).ravel()

    def psi(self, q) -> np.ndarray:
        return np.asarray(self.fns.psi(q))


def eigen_mean(quaternions: np.ndarray, weights: np.ndarray, q_ref: np.ndarray) -> np.ndarray:
    """Eqs (36)-(38) with LAPACK: eigenvector of N = Σ W_i Ψ(q_i) Ψ(q_i)ᵀ for its smallest eigenvalue."""
    psi = _Functions.get().psi
    N = sum(w * psi(q) @ psi(q).T for w, q in zip(weights, quaternions))
    _, vectors = np.linalg.eigh(N)
    mean = vectors[:, 0]
    return mean if mean @ q_ref >= 0 else -mean


class ReferenceAttitudeFilter:
    """The NumPy reference of :class:`AttitudeFilter` (same arguments, predict/update/step)."""

    def __init__(self, kind: str, q0, b0, P0, Q=None, R=None, kappa: float = DEFAULT_KAPPA):
        if kind not in KINDS:
            raise ValueError(f"kind: expected one of {KINDS}, got {kind!r}")
        self.kind = kind
        self.x, self.P = _initial_state(q0, b0, P0)
        self.Q = model.process_noise_psd() if Q is None else as_array("Q", Q, (6, 6))
        self.R = model.star_tracker_covariance() if R is None else as_array("R", R, (3, 3))
        self.kappa = float(kappa)
        self.f = _Functions.get()
        self.y, self.S = np.zeros(3), np.zeros((3, 3))

    @property
    def q(self) -> np.ndarray:
        return self.x[0:4]

    @property
    def b(self) -> np.ndarray:
        return self.x[4:7]

    def predict(self, omega_g, dt: float) -> None:
        if self.kind == "aukf":
            self.step(omega_g, dt, None)
        else:
            self.x, self.P = getattr(self, f"_{self.kind}_predict")(np.asarray(omega_g, float), dt)

    def update(self, q_s) -> None:
        if self.kind == "aukf":
            raise ValueError("update: the augmented UKF updates only inside step(omega_g, dt, q_s)")
        z = _checked_measurement(_measurement(q_s))
        self.x, self.P, self.y, self.S = getattr(self, f"_{self.kind}_update")(z)

    def step(self, omega_g, dt: float, q_s=None) -> None:
        if self.kind != "aukf":
            self.predict(omega_g, dt)
            if q_s is not None:
                self.update(q_s)
            return
        z = None if q_s is None else _checked_measurement(_measurement(q_s))
        self.x, self.P, y, S = self._aukf_step(np.asarray(omega_g, float), dt, z)
        if z is not None:
            self.y, self.S = y, S

    # -------------------------------------------------------------- MEKF
    def _mekf_predict(self, omega_g, dt):
        q, b = self.f.propagate(self.q, self.b, omega_g, np.zeros(3), np.zeros(3), dt)
        F, G = (np.asarray(m) for m in self.f.transition(self.x, omega_g, dt))
        P = F @ self.P @ F.T + G @ (self.Q / dt) @ G.T
        return np.concatenate([q, b]), 0.5 * (P + P.T)

    def _mekf_update(self, z):
        H, D = (np.asarray(m) for m in self.f.measurement(self.x))
        R = D @ self.R @ D.T
        S = H @ self.P @ H.T + R
        _cholesky(S)
        K = np.linalg.solve(S, H @ self.P).T
        innovation = self.f.error_vector(z, self.q)
        I_KH = np.eye(6) - K @ H
        P = I_KH @ self.P @ I_KH.T + K @ R @ K.T
        return self._corrected(K @ innovation, self.q, self.b), 0.5 * (P + P.T), innovation, S

    # -------------------------------------------------------------- paper's UKF
    def _sigma(self, covariances, dimension):
        factor = _block_cholesky(covariances)
        gamma = np.sqrt(dimension + self.kappa) if dimension + self.kappa > 0 else _domain("n + kappa <= 0")
        columns = [gamma * factor[:, i] for i in range(factor.shape[1])]
        offsets = [np.zeros(factor.shape[0])] + columns + [-c for c in columns]
        scale = dimension + self.kappa
        weights = np.array([self.kappa / scale] + [0.5 / scale] * (2 * dimension))
        return offsets, weights

    def _propagate_set(self, offsets, weights, q_hat, b_hat, omega_g, dt):
        q_points, b_points = [], []
        for o in offsets:
            q_i, b_i, ok = self.f.perturb(o[0:6], q_hat, b_hat)
            if not ok:
                _domain("a sigma vector has |δp| >= 1 (eq 41)")
            q_next, b_next = self.f.propagate(q_i, b_i, omega_g, o[6:9], o[9:12], dt)
            q_points.append(q_next)
            b_points.append(b_next)
        q_mean = eigen_mean(q_points, weights, q_points[0])
        b_mean = sum(w * b for w, b in zip(weights, b_points))
        deviations = [np.concatenate([self.f.error_vector(q, q_mean), b - b_mean]) for q, b in zip(q_points, b_points)]
        P = sum(w * np.outer(d, d) for w, d in zip(weights, deviations))
        return q_points, q_mean, b_mean, deviations, 0.5 * (P + P.T)

    def _ukf_predict(self, omega_g, dt):
        offsets, weights = self._sigma([self.P, self.Q / dt], 12)
        _, q_mean, b_mean, _, P = self._propagate_set(offsets, weights, self.q, self.b, omega_g, dt)
        return np.concatenate([q_mean, b_mean]), P

    def _sigma_update(self, q_hat, b_hat, P, deviations, q_points, eta_points, weights, z):
        z_points = [self.f.star_tracker(q, eta) for q, eta in zip(q_points, eta_points)]
        z_mean = eigen_mean(z_points, weights, z_points[0])
        dz = [self.f.error_vector(zi, z_mean) for zi in z_points]
        P_yy = sum(w * np.outer(d, d) for w, d in zip(weights, dz))
        P_xy = sum(w * np.outer(a, d) for w, a, d in zip(weights, deviations, dz))
        _cholesky(P_yy)
        K = np.linalg.solve(P_yy, P_xy.T).T
        innovation = self.f.error_vector(z, z_mean)
        P_new = P - K @ P_yy @ K.T
        return self._corrected(K @ innovation, q_hat, b_hat), 0.5 * (P_new + P_new.T), innovation, P_yy

    def _ukf_update(self, z):
        offsets, weights = self._sigma([self.P, self.R], 9)
        q_points = []
        for o in offsets:
            q_i, _, ok = self.f.perturb(o[0:6], self.q, self.b)
            if not ok:
                _domain("a sigma vector has |δp| >= 1 (eq 48)")
            q_points.append(q_i)
        return self._sigma_update(self.q, self.b, self.P, [o[0:6] for o in offsets], q_points,
                                  [o[6:9] for o in offsets], weights, z)

    # -------------------------------------------------------------- augmented UKF
    def _aukf_step(self, omega_g, dt, z):
        offsets, weights = self._sigma([np.block([[self.P, np.zeros((6, 9))],
                                                  [np.zeros((9, 6)), _block_diag(self.Q / dt, self.R)]])], 15)
        q_points, q_mean, b_mean, deviations, P = self._propagate_set(offsets, weights, self.q, self.b, omega_g, dt)
        x_pred = np.concatenate([q_mean, b_mean])
        if z is None:
            return x_pred, P, None, None
        return self._sigma_update(q_mean, b_mean, P, deviations, q_points, [o[12:15] for o in offsets], weights, z)

    def _corrected(self, correction, q_hat, b_hat) -> np.ndarray:
        q, b, ok = self.f.perturb(correction, q_hat, b_hat)
        if not ok:
            _domain("the correction has |δp| >= 1 (eq 52)")
        return np.concatenate([q / np.linalg.norm(q), b])


def _checked_measurement(z: np.ndarray) -> np.ndarray:
    norm = np.linalg.norm(z)
    if abs(norm - 1) > family.MEASUREMENT_NORM_TOLERANCE:
        raise SymkfError("reference update", STATUS_DOMAIN, f"|q_s| = {norm:.6g}")
    return z / norm


def _domain(detail: str):
    raise SymkfError("reference", STATUS_DOMAIN, detail)


def _cholesky(A: np.ndarray) -> np.ndarray:
    if not np.isfinite(A).all():
        raise SymkfError("reference", STATUS_NONFINITE)
    try:
        return np.linalg.cholesky(A)
    except np.linalg.LinAlgError:
        raise SymkfError("reference", STATUS_NOT_PD) from None


def _block_diag(*blocks) -> np.ndarray:
    size = sum(b.shape[0] for b in blocks)
    out, i = np.zeros((size, size)), 0
    for b in blocks:
        out[i:i + b.shape[0], i:i + b.shape[0]] = b
        i += b.shape[0]
    return out


def _block_cholesky(blocks) -> np.ndarray:
    return _block_diag(*[_cholesky(b) for b in blocks])


def attitude_filter(kind: str, q0, b0, P0, backend: str = "auto", **options) -> AttitudeFilter:
    """Load (building if stale) the attitude model and return its ``kind`` filter."""
    from . import load
    return AttitudeFilter(load("attitude", backend=backend), kind, q0, b0, P0, **options)


#: Older name of the run result.
AttitudeRun = RunResult

__all__ = ["AttitudeFilter", "AttitudeRun", "ReferenceAttitudeFilter", "attitude_filter", "eigen_mean",
           "unit_quaternion"]

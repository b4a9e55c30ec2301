"""Paper 000's MEKF, UKF and augmented UKF written as the paper writes them, in NumPy: the oracle
that the generic manifold families, with the attitude model's options, are paper 000.

Shuster product, δp charts, eqs (34)-(53); the quaternion mean by ``numpy.linalg.eigh``. The
compiled filters are the generic families ("mekf" in ``codegen/families/mekf.py``,
"sukf"/"aukf" in ``quaternion_filters.py``)."""
from __future__ import annotations

import casadi as ca
import numpy as np

from symkf.codegen.families import manifold as manifold_family
from symkf.codegen.families import quaternion_filters as family
from symkf.codegen.spec import STATUS_DOMAIN, STATUS_NONFINITE, STATUS_NOT_PD
from symkf.models import attitude as model
from symkf.models import quaternion as quat
from symkf.runtime.backends import SymkfError
from symkf.runtime.contract import as_array, covariance


#: Largest accepted deviation of an initial quaternion's norm from 1 (smaller ones are normalised).
NORM_TOLERANCE = manifold_family.MEASUREMENT_NORM_TOLERANCE
#: UKF scaling κ used unless given (paper 000 leaves κ open).
DEFAULT_KAPPA = family.DEFAULT_KAPPA
KINDS = ("mekf", "ukf", "aukf")


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


class _Functions:
    """The paper's equations as CasADi Functions the reference evaluates (built once per process):
    the model's step (44)-(45) and star tracker (30) from models/attitude.py, and the paper's own
    error charts in its Shuster product (23): δp of δq = q ⊗ q̂⁻¹ (34), q = δq(δp) ⊗ q̂ (41)."""

    _instance = None

    @classmethod
    def get(cls) -> "_Functions":
        if cls._instance is None:
            cls._instance = cls()
        return cls._instance

    def __init__(self):
        q, q_ref, b = ca.SX.sym("q", 4), ca.SX.sym("q_ref", 4), ca.SX.sym("b", 3)
        omega_g, eta_a, eta_b = ca.SX.sym("omega_g", 3), ca.SX.sym("eta_a", 3), ca.SX.sym("eta_b", 3)
        eta_s, dt, delta_x = ca.SX.sym("eta_s", 3), ca.SX.sym("dt"), ca.SX.sym("delta_x", 6)
        self._propagate = ca.Function("propagate", [q, b, omega_g, eta_a, eta_b, dt],
                                      list(model.propagate(q, b, omega_g, eta_a, eta_b, dt)))
        self._star = ca.Function("star_tracker", [q, eta_s], [model.star_tracker(q, eta_s)])
        self._error_vector = ca.Function("error_vector", [q, q_ref], [_paper_error_vector(q, q_ref)])
        delta_q, ok = quat.quaternion_from_error_vector(delta_x[0:3])
        self._perturb = ca.Function("perturb", [delta_x, q, b], [quat.otimes(delta_q, q), b + delta_x[3:6], ok])
        self._psi = ca.Function("psi", [q], [quat.psi_matrix(q)])
        self.transition, self.measurement = self._jacobians()

    def _jacobians(self):
        """F = ∂δx⁺/∂δx, G = ∂δx⁺/∂w of (44)-(45) and H = ∂δp_s/∂δx, D = ∂δp_s/∂η_s of (30), (50),
        derived by CasADi through the paper's charts at δx = 0, w = 0, η_s = 0."""
        x, u, dt = ca.SX.sym("x", 7), ca.SX.sym("u", 3), ca.SX.sym("dt")
        delta_x, w, eta_s = ca.SX.sym("delta_x", 6), ca.SX.sym("w", 6), ca.SX.sym("eta_s", 3)
        q_hat, b_hat = x[0:4], x[4:7]
        q, b, _ = self._perturb(delta_x, q_hat, b_hat)
        q_next, b_next = self._propagate(q, b, u, w[0:3], w[3:6], dt)
        q_nominal, b_nominal = self._propagate(q_hat, b_hat, u, ca.SX.zeros(3), ca.SX.zeros(3), dt)
        delta_next = ca.vertcat(_paper_error_vector(q_next, q_nominal), b_next - b_nominal)
        zero = ca.SX.zeros(12)
        F = ca.substitute(ca.jacobian(delta_next, delta_x), ca.vertcat(delta_x, w), zero)
        G = ca.substitute(ca.jacobian(delta_next, w), ca.vertcat(delta_x, w), zero)
        delta_ps = _paper_error_vector(self._star(q, eta_s), q_hat)
        zero = ca.SX.zeros(9)
        H = ca.substitute(ca.jacobian(delta_ps, delta_x), ca.vertcat(delta_x, eta_s), zero)
        D = ca.substitute(ca.jacobian(delta_ps, eta_s), ca.vertcat(delta_x, eta_s), zero)
        return (ca.Function("transition", [x, u, dt], [F, G]), ca.Function("measurement", [x], [H, D]))

    def perturb(self, delta_x, q, b):
        q_i, b_i, ok = self._perturb(delta_x, q, b)
        return np.asarray(q_i).ravel(), np.asarray(b_i).ravel(), bool(ok)

    def propagate(self, q, b, omega_g, eta_a, eta_b, dt):
        q_next, b_next = self._propagate(q, b, omega_g, eta_a, eta_b, dt)
        return np.asarray(q_next).ravel(), np.asarray(b_next).ravel()

    def star_tracker(self, q, eta_s) -> np.ndarray:
        return np.asarray(self._star(q, eta_s)).ravel()

    def error_vector(self, q, q_ref) -> np.ndarray:
        return np.asarray(self._error_vector(q, q_ref)).ravel()

    def psi(self, q) -> np.ndarray:
        return np.asarray(self._psi(q))


def _paper_error_vector(q, q_ref):
    """Eq (34): δp of δq = q ⊗ q_ref⁻¹ (Shuster product), sign chosen so that δq4 >= 0."""
    delta_q = quat.error_quaternion(q, q_ref)
    return ca.if_else(delta_q[3] < 0, -1, 1) * delta_q[0:3]


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
    if abs(norm - 1) > NORM_TOLERANCE:
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

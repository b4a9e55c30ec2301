"""NumPy reference of the square-root filters (codegen/families/srukf.py, srekf.py): the factor
L of P = L L^T carried, QR (numpy.linalg.qr) and rank-one Cholesky updates/downdates written out.

- SR-UKF: Van der Merwe & Wan, ICASSP 2001, Algorithm 3.1 (its time and measurement updates), Julier weights;
- SR-EKF: the array form (Kailath, Sayed & Hassibi, Linear Estimation, sec. 12.3): prediction
  L- = qr[F L, sqrt(Q_d)], update by triangularising [[chol(R), H L], [0, L]].

The model is evaluated through CasADi (the same Functions the C code calls); compiled and
reference filters agree to round-off (tests/runtime/test_square_root_filters.py)."""
from __future__ import annotations

import numpy as np
from scipy.linalg import solve_triangular

from symkf.runtime.covariance_form import psd_factor
from .common import wrap_angle
from .kalman import ReferenceFilter


def triangularize(A: np.ndarray) -> np.ndarray:
    """Lower L, diagonal >= 0, with L L^T = A A^T (QR of A^T; column signs made non-negative)."""
    n, m = A.shape
    B = A.T if m >= n else np.vstack([A.T, np.zeros((n - m, n))])
    R = np.linalg.qr(B, mode="r")[:n]
    L = R.T.copy()
    L *= np.where(np.diag(L) < 0, -1.0, 1.0)
    return L


def cholesky_update(L: np.ndarray, v: np.ndarray, sigma: int) -> np.ndarray:
    """The lower factor of L L^T + sigma v v^T (cholupdate); ValueError if a downdate fails."""
    L, v = L.copy(), np.array(v, float)
    for k in range(L.shape[0]):
        d = L[k, k] ** 2 + sigma * v[k] ** 2
        if sigma < 0 and v[k] == 0:
            continue
        if d <= 0 or (sigma < 0 and L[k, k] <= 0):
            raise ValueError("Cholesky downdate: the result is not positive definite")
        if d == 0:
            continue
        r = np.sqrt(d)
        if sigma > 0:
            c, s = L[k, k] / r, v[k] / r
            col = L[k + 1:, k].copy()
            L[k + 1:, k] = c * col + s * v[k + 1:]
            v[k + 1:] = c * v[k + 1:] - s * col
        else:
            c, s = r / L[k, k], v[k] / L[k, k]
            L[k + 1:, k] = (L[k + 1:, k] - s * v[k + 1:]) / c
            v[k + 1:] = c * v[k + 1:] - s * L[k + 1:, k]
        L[k, k] = r
    return L


def weighted_factor(weights, deviations, extra: np.ndarray) -> np.ndarray:
    """Factor of sum_i W_i d_i d_i^T + extra extra^T: QR of sqrt(W_1) d_1.., extra; then d_0 by W_0."""
    A = np.column_stack([np.sqrt(weights[1]) * d for d in deviations[1:]] + [extra])
    L = triangularize(A)
    w0 = weights[0]
    if w0 > 0:
        L = cholesky_update(L, np.sqrt(w0) * deviations[0], +1)
    elif w0 < 0:
        L = cholesky_update(L, np.sqrt(-w0) * deviations[0], -1)
    return L


class CarriesFactor:
    """What every square-root reference shares: ``L`` carried; ``P`` reads L L^T (symmetrised) and
    setting ``P`` stores its factor (:func:`~symkf.runtime.covariance_form.psd_factor`)."""

    @property
    def P(self) -> np.ndarray:
        P = self.L @ self.L.T
        return 0.5 * (P + P.T)

    @P.setter
    def P(self, value) -> None:
        self.L = psd_factor(value)


class SquareRootReference(CarriesFactor, ReferenceFilter):
    """SR-UKF ("srukf") or SR-EKF ("srekf") in NumPy; ``L`` carried, ``P`` = L L^T read."""

    FAMILIES = ("srukf", "srekf")

    def __init__(self, model_name, family: str, x0, P0, Q, R: dict | None = None, p=None,
                 kappa: float = 0.0, **overrides):
        if family not in self.FAMILIES:
            raise ValueError(f"family: expected one of {self.FAMILIES}")
        super().__init__(model_name, "ekf", x0, P0, Q, R, p, kappa, **overrides)
        self.family = family
        self.propagation = self.functions.for_filter(family)     # P0 was factored by CarriesFactor

    # ---------------------------------------------------------------- noise
    def noise_factor(self, t: float, dt: float) -> np.ndarray:
        C = psd_factor(self.Q) * np.sqrt(dt)
        if self.functions.noise_gain is None:
            return C
        return np.array(self.functions.noise_gain(t, self.x, self.u, self.p)) @ C

    # ---------------------------------------------------------------- steps
    def predict(self, t: float, dt: float) -> None:
        noise = self.noise_factor(t, dt)
        if self.family == "srekf":
            F = np.array(self.propagation.jac_fd(t, dt, self.x, self.u, self.p))
            self.x = self._fd(t, dt, self.x)
            self.L = triangularize(np.hstack([F @ self.L, noise]))
            return
        points, weights = self._points(self.x)
        moved = [self._fd(t, dt, pt) for pt in points]
        x = sum(w * pt for w, pt in zip(weights, moved))
        self.L = weighted_factor(weights, [pt - x for pt in moved], noise)
        self.x = x

    def update(self, z, name: str, t: float, q, mask=None) -> None:
        z = np.asarray(z, float)
        mask = np.ones_like(z) if mask is None else np.asarray(mask, float)
        R_root = np.linalg.cholesky(self.masked_noise(self.R[name], mask))
        wrap = self.wrap[name]
        n, m = len(self.x), len(z)
        if self.family == "srekf":
            z_pred = self._h(name, t, self.x, q)
            H = mask[:, None] * np.array(self.functions.jac_h[name](t, self.x, self.u, self.p, q))
            y = self.innovation(z, z_pred, mask, wrap)
            pre = np.block([[R_root, H @ self.L], [np.zeros((n, m)), self.L]])
            post = triangularize(pre)
            S_z, K_bar, L_new = post[:m, :m], post[m:, :m], post[m:, m:]
            self.x = self.x + K_bar @ solve_triangular(S_z, y, lower=True)
        else:
            points, weights = self._points(self.x)
            predicted = [self._h(name, t, pt, q) for pt in points]
            ref = predicted[0]
            z_pred = ref + sum(w * np.where(wrap, wrap_angle(zi - ref), zi - ref) for w, zi in zip(weights, predicted))
            dz = [mask * np.where(wrap, wrap_angle(zi - z_pred), zi - z_pred) for zi in predicted]
            S_z = weighted_factor(weights, dz, R_root)
            Pxz = sum(w * np.outer(pt - self.x, d) for w, pt, d in zip(weights, points, dz))
            V = solve_triangular(S_z, Pxz.T, lower=True)          # U = K S_z = V^T
            y = self.innovation(z, z_pred, mask, wrap)
            self.x = self.x + V.T @ solve_triangular(S_z, y, lower=True)
            L_new = self.L
            for j in range(m):
                L_new = cholesky_update(L_new, V[j], -1)
        self.L = L_new
        self.y, self.S = y, S_z @ S_z.T

    # ---------------------------------------------------------------- algebra
    def _points(self, x):
        n = len(x)
        root = np.sqrt(n + self.kappa)
        points = [x] + [x + root * self.L[:, i] for i in range(n)] + [x - root * self.L[:, i] for i in range(n)]
        weights = [self.kappa / (n + self.kappa)] + [0.5 / (n + self.kappa)] * (2 * n)
        return points, weights

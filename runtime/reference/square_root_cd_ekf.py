"""NumPy reference of the square-root continuous-discrete EKF (``codegen/families/srcdekf.py``):
per RK4 sub-step, x' = a(x), Phi' = A Phi (Phi(0) = I) and Q_d' = A Q_d + Q_d A^T + Q (Q_d(0) = 0)
integrated together, then L = qr[Phi L, chol(Q_d)]; the update by triangularising
[[chol(R), H L], [0, L]] (Kailath, Sayed & Hassibi, Linear Estimation, 2000, sec. 12.3). The model
functions are :func:`~symkf.codegen.families.cd_ekf.reference_functions`, as the CD-EKF's reference."""
from __future__ import annotations

import numpy as np
from scipy.linalg import solve_triangular

from symkf.runtime.covariance_form import psd_factor
from .cd_ekf import NumpyCDEKF
from .common import wrap_angle
from .square_root import CarriesFactor, triangularize


class NumpySquareRootCDEKF(CarriesFactor, NumpyCDEKF):
    """The square-root CD-EKF in NumPy; ``L`` carried, ``P`` = L L^T read."""

    def _rates(self, t, x, Phi, Qd):
        a = np.asarray(self.functions["a"](t, x, self.u, self.p)).ravel()
        A = np.asarray(self.functions["A"](t, x, self.u, self.p))
        return a, A @ Phi, A @ Qd + Qd @ A.T + self.Q

    def predict(self, t: float, dt: float, u=None) -> None:
        if u is not None:
            self.u = np.array(u, float)
        x, L, h, n = self.x, self.L, dt / self.substeps, self.x.size
        for i in range(self.substeps):
            ti = t + i * h
            state = (x, np.eye(n), np.zeros((n, n)))
            k1 = self._rates(ti, *state)
            k2 = self._rates(ti + h / 2, *(v + h / 2 * k for v, k in zip(state, k1)))
            k3 = self._rates(ti + h / 2, *(v + h / 2 * k for v, k in zip(state, k2)))
            k4 = self._rates(ti + h, *(v + h * k for v, k in zip(state, k3)))
            x, Phi, Qd = (v + h / 6 * (a + 2 * b + 2 * c + d) for v, a, b, c, d in zip(state, k1, k2, k3, k4))
            L = triangularize(np.hstack([Phi @ L, psd_factor(0.5 * (Qd + Qd.T))]))
        self.x, self.L, self.t = x, L, t + dt

    def update(self, z, measurement: str, mask=None, **_ignored) -> None:
        z = np.asarray(z, float)
        mask = np.ones(z.size) if mask is None else np.asarray(mask, float)
        z_pred, H = self.functions[f"h_{measurement}"](self.t, self.x, self.u, self.p, [])
        z_pred, H = np.asarray(z_pred).ravel(), np.asarray(H.full()) * mask[:, None]
        R_root = np.linalg.cholesky(self.R[measurement] * np.outer(mask, mask) + np.diag(1.0 - mask))
        y = np.where(mask > 0.5, np.nan_to_num(z) - z_pred, 0.0)
        wrap = self.wrap[measurement]
        y[wrap] = wrap_angle(y[wrap])
        m, n = z.size, self.x.size
        post = triangularize(np.block([[R_root, H @ self.L], [np.zeros((n, m)), self.L]]))
        S_z, K_bar = post[:m, :m], post[m:, :m]
        self.x = self.x + K_bar @ solve_triangular(S_z, y, lower=True)
        self.L = post[m:, m:]

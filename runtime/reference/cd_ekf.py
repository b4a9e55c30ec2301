"""NumPy reference of the continuous-discrete EKF of paper 003 (``codegen/families/cd_ekf.py``)."""
from __future__ import annotations

import numpy as np

from symkf.codegen.families.cd_ekf import reference_functions
from .common import wrap_angle


class NumpyCDEKF:
    """Plain-NumPy continuous-discrete EKF with the compiled filter's interface (the oracle).

    Same equations as ``symkf.codegen.families.cd_ekf`` (Table 1): RK4 of x and the full P, then
    masked updates with P = (I - K H) P symmetrised; the model functions come from the same
    symbolic source via :func:`reference_functions`.
    """

    def __init__(self, model, x0, P0, Q, R: dict, substeps: int = 1):
        self.functions = reference_functions(model)
        self.wrap = {name: np.array(meas.wrap) for name, meas in model.measurements.items()}
        self.x, self.P, self.Q = np.array(x0, float), np.array(P0, float), np.array(Q, float)
        self.R = {name: np.array(value, float) for name, value in R.items()}
        self.substeps, self.t, self.u = substeps, 0.0, np.zeros(model.u.shape[0])
        self.p = np.zeros(model.p.shape[0])

    def _derivative(self, t, x, P):
        a = np.asarray(self.functions["a"](t, x, self.u, self.p)).ravel()
        A = np.asarray(self.functions["A"](t, x, self.u, self.p))
        return a, A @ P + P @ A.T + self.Q

    def predict(self, t: float, dt: float, u=None) -> None:
        if u is not None:
            self.u = np.array(u, float)
        x, P, h = self.x, self.P, dt / self.substeps
        for i in range(self.substeps):
            ti = t + i * h
            k1 = self._derivative(ti, x, P)
            k2 = self._derivative(ti + h / 2, x + h / 2 * k1[0], P + h / 2 * k1[1])
            k3 = self._derivative(ti + h / 2, x + h / 2 * k2[0], P + h / 2 * k2[1])
            k4 = self._derivative(ti + h, x + h * k3[0], P + h * k3[1])
            x = x + h / 6 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0])
            P = P + h / 6 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1])
        self.x, self.P, self.t = x, 0.5 * (P + P.T), t + dt

    def update(self, z, measurement: str, mask=None, **_ignored) -> None:
        z = np.asarray(z, float)
        mask = np.ones(z.size) if mask is None else np.asarray(mask, float)
        z_pred, H = self.functions[f"h_{measurement}"](self.t, self.x, self.u, self.p, [])
        z_pred, H = np.asarray(z_pred).ravel(), np.asarray(H.full()) * mask[:, None]
        R = self.R[measurement] * np.outer(mask, mask) + np.diag(1.0 - mask)
        innovation = np.where(mask > 0.5, np.nan_to_num(z) - z_pred, 0.0)
        wrap = self.wrap[measurement]
        innovation[wrap] = wrap_angle(innovation[wrap])
        U = H @ self.P
        S = U @ H.T + R
        K = np.linalg.solve(S, U).T
        P = self.P - K @ U
        self.x, self.P = self.x + K @ innovation, 0.5 * (P + P.T)

"""NumPy reference of the continuous-discrete EKF of paper 003 (``codegen/families/cd_ekf.py``)."""
from __future__ import annotations

import numpy as np

from symkf.codegen.families.cd_ekf import reference_functions
from .common import wrap_angle


class NumpyCDEKF:
    """Plain-NumPy continuous-discrete EKF with the compiled filter's interface (the oracle).

    Same equations as ``symkf.codegen.families.cd_ekf`` (Table 1): RK4 of x and the full P, then
    masked updates with P = (I - K H) P symmetrised; the model functions come from the same
    symbolic source via :func:`reference_functions`. :meth:`transition` adds the smoother's
    transition matrix Phi to the same RK4 (``symkf.runtime.reference.rts.cd_ekf_rts``).
    """

    def __init__(self, model, x0, P0, Q, R: dict, substeps: int = 1):
        self.functions = reference_functions(model)
        self.wrap = {name: np.array(meas.wrap) for name, meas in model.measurements.items()}
        self.x, self.P, self.Q = np.array(x0, float), np.array(P0, float), np.array(Q, float)
        self.R = {name: np.array(value, float) for name, value in R.items()}
        self.substeps, self.t, self.u = substeps, 0.0, np.zeros(model.u.shape[0])
        self.p = np.zeros(model.p.shape[0])

    def _derivative(self, t, x, P, *Phi):
        a = np.asarray(self.functions["a"](t, x, self.u, self.p)).ravel()
        A = np.asarray(self.functions["A"](t, x, self.u, self.p))
        return (a, A @ P + P @ A.T + self.Q) + tuple(A @ M for M in Phi)

    def _integrate(self, t: float, dt: float, x, P, transition: bool = False):
        """RK4 over [t, t + dt] of x, P (and with ``transition`` the transition matrix,
        Phi' = A(x) Phi, Phi(t) = I: the filter itself does not need it)."""
        y, h = (x, P) + ((np.eye(x.size),) if transition else ()), dt / self.substeps
        for i in range(self.substeps):
            ti = t + i * h
            k1 = self._derivative(ti, *y)
            k2 = self._derivative(ti + h / 2, *(a + h / 2 * b for a, b in zip(y, k1)))
            k3 = self._derivative(ti + h / 2, *(a + h / 2 * b for a, b in zip(y, k2)))
            k4 = self._derivative(ti + h, *(a + h * b for a, b in zip(y, k3)))
            y = tuple(a + h / 6 * (b1 + 2 * b2 + 2 * b3 + b4) for a, b1, b2, b3, b4 in zip(y, k1, k2, k3, k4))
        return (y[0], 0.5 * (y[1] + y[1].T)) + y[2:]

    def predict(self, t: float, dt: float, u=None) -> None:
        if u is not None:
            self.u = np.array(u, float)
        self.x, self.P = self._integrate(t, dt, self.x, self.P)
        self.t = t + dt

    def transition(self, t: float, dt: float, x, P, u=None):
        """x^-, P^- and Phi = d x^- / d x of the time update from (x, P) at t (the smoother's step)."""
        if u is not None:
            self.u = np.array(u, float)
        return self._integrate(t, dt, np.asarray(x, float), np.asarray(P, float), transition=True)

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

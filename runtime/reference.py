"""NumPy reference EKF and UKF: the readable oracle (and the "plain Python" timing column).

The model is evaluated through CasADi (the same f_d, F, h, H Functions the C code calls); the
filter algebra is written out in NumPy exactly as ``codegen/families/kalman.py`` generates it:
EKF with the Joseph-form update, UKF with Julier sigma points (paper 004 eqs (1)-(3)) redrawn for
the update, masks and angle wrapping identical. Compiled and reference filters must agree to
round-off on the same inputs (tests/test_reference_agreement.py).
"""
from __future__ import annotations

import numpy as np
from scipy.linalg import cho_factor, cho_solve, solve_triangular

from symkf.codegen import make_config
from symkf.codegen.families.cd_ekf import reference_functions
from symkf.codegen.kernels import ModelFunctions
from symkf.models import get_model


def wrap_angle(a):
    """Wrap to (-pi, pi], the same formula as the generated code (codegen.linalg.wrap_angle)."""
    return a - 2 * np.pi * np.ceil((a - np.pi) / (2 * np.pi))


class ReferenceFilter:
    """EKF ("ekf") or UKF ("ukf") in plain NumPy, same conventions as the compiled filters."""

    def __init__(self, model_name: str, family: str, x0, P0, Q, R: dict | None = None, p=None,
                 kappa: float = 0.0):
        if family not in ("ekf", "ukf"):
            raise ValueError("family: expected 'ekf' or 'ukf'")
        model = get_model(model_name)
        self.functions = ModelFunctions(model, make_config(model_name))
        self.family, self.kappa = family, float(kappa)
        self.x, self.P, self.Q = np.array(x0, float), np.array(P0, float), np.array(Q, float)
        self.p = np.array(model.param_defaults if p is None else p, float)
        self.u = np.zeros(len(model.inputs))
        self.wrap = {name: np.array(m.wrap) for name, m in model.measurements.items()}
        self.R = {name: np.diag(m.sigma**2) for name, m in model.measurements.items()}
        self.R.update(R or {})
        self.y = self.S = None

    # ---------------------------------------------------------------- model calls
    def _fd(self, t, dt, x):
        return np.array(self.functions.fd(t, dt, x, self.u, self.p)).ravel()

    def _h(self, name, t, x, q):
        return np.array(self.functions.h[name](t, x, self.u, self.p, q)).ravel()

    # ---------------------------------------------------------------- steps
    def predict(self, t: float, dt: float) -> None:
        noise = self.process_noise(t, dt)
        if self.family == "ekf":
            F = np.array(self.functions.jac_fd(t, dt, self.x, self.u, self.p))
            self.x = self._fd(t, dt, self.x)
            self.P = _sym(F @ self.P @ F.T + noise)
            return
        points, weights = self._sigma_points(self.x, self.P)
        propagated = [self._fd(t, dt, pt) for pt in points]
        x = sum(w * pt for w, pt in zip(weights, propagated))
        P = sum(w * np.outer(pt - x, pt - x) for w, pt in zip(weights, propagated)) + noise
        self.x, self.P = x, _sym(P)

    def process_noise(self, t: float, dt: float) -> np.ndarray:
        """Q dt (additive), or G Q G^T dt with G = df/dw at the step start (a model with noise())."""
        if self.functions.noise_gain is None:
            return self.Q * dt
        G = np.array(self.functions.noise_gain(t, self.x, self.u, self.p))
        return G @ self.Q @ G.T * dt

    def update(self, z, name: str, t: float, q, mask=None) -> None:
        z = np.asarray(z, float)
        mask = np.ones_like(z) if mask is None else np.asarray(mask, float)
        R = self.masked_noise(self.R[name], mask)
        wrap = self.wrap[name]
        if self.family == "ekf":
            z_pred = self._h(name, t, self.x, q)
            H = mask[:, None] * np.array(self.functions.jac_h[name](t, self.x, self.u, self.p, q))
            y = self.innovation(z, z_pred, mask, wrap)
            S = _sym(H @ self.P @ H.T + R)
            K = cho_solve(cho_factor(S, lower=True), H @ self.P).T
            I_KH = np.eye(len(self.x)) - K @ H
            self.x = self.x + K @ y
            self.P = _sym(I_KH @ self.P @ I_KH.T + K @ R @ K.T)
        else:
            points, weights = self._sigma_points(self.x, self.P)
            predicted = [self._h(name, t, pt, q) for pt in points]
            ref = predicted[0]
            z_pred = ref + sum(w * np.where(wrap, wrap_angle(zi - ref), zi - ref) for w, zi in zip(weights, predicted))
            dz = [mask * np.where(wrap, wrap_angle(zi - z_pred), zi - z_pred) for zi in predicted]
            dx = [pt - self.x for pt in points]
            S = _sym(sum(w * np.outer(d, d) for w, d in zip(weights, dz)) + R)
            Pxz = sum(w * np.outer(a, b) for w, a, b in zip(weights, dx, dz))
            L = np.linalg.cholesky(S)
            U = solve_triangular(L, Pxz.T, lower=True)     # K y = U^T L^-1 y, K S K^T = U^T U
            y = self.innovation(z, z_pred, mask, wrap)
            self.x = self.x + U.T @ solve_triangular(L, y, lower=True)
            self.P = _sym(self.P - U.T @ U)
        self.y, self.S = y, S

    def step(self, t: float, dt: float, z, name: str, q, mask=None) -> None:
        self.predict(t, dt)
        self.update(z, name, t + dt, q, mask)

    # ---------------------------------------------------------------- algebra
    def _sigma_points(self, x, P):
        n = len(x)
        L = np.linalg.cholesky((n + self.kappa) * P)
        points = [x] + [x + L[:, i] for i in range(n)] + [x - L[:, i] for i in range(n)]
        weights = [self.kappa / (n + self.kappa)] + [0.5 / (n + self.kappa)] * (2 * n)
        return points, weights

    @staticmethod
    def masked_noise(R, mask):
        return R * np.outer(mask, mask) + np.diag(1 - mask)

    @staticmethod
    def innovation(z, z_pred, mask, wrap):
        d = np.where(wrap, wrap_angle(z - z_pred), z - z_pred)
        return np.where(mask > 0.5, d, 0.0)


def _sym(A):
    return 0.5 * (A + A.T)


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

"""NumPy reference of the EKF (Joseph-form update) and the UKF (Julier sigma points, paper 004
eqs (1)-(3), redrawn for the update), as ``codegen/families/kalman.py`` generates them.

The model is evaluated through CasADi (the same Functions the C code calls); masks and angle
wrapping are identical to the compiled filters, which agree with it to round-off
(tests/test_contract.py)."""
from __future__ import annotations

import numpy as np
from scipy.linalg import cho_factor, cho_solve, solve_triangular

from symkf.codegen import make_config
from symkf.codegen.model_functions import ModelFunctions
from symkf.models import get_model
from symkf.models.estimation import augmented
from .common import _init_filter_state, _sym, wrap_angle


class ReferenceFilter:
    """EKF ("ekf") or UKF ("ukf") in plain NumPy, same conventions as the compiled filters."""

    def __init__(self, model_name: str, family: str, x0, P0, Q, R: dict | None = None, p=None,
                 kappa: float = 0.0, **overrides):
        if family not in ("ekf", "ukf"):
            raise ValueError("family: expected 'ekf' or 'ukf'")
        model = augmented(get_model(model_name))          # estimated parameters as states, as generated
        self.functions = ModelFunctions(model, make_config(model_name, **overrides))
        self.propagation = self.functions.for_filter(family)     # the family's discretisation
        self.family, self.kappa = family, float(kappa)
        _init_filter_state(self, model, x0, P0, Q, p, R)

    # ---------------------------------------------------------------- model calls
    def _fd(self, t, dt, x):
        return np.array(self.propagation.fd(t, dt, x, self.u, self.p)).ravel()

    def _h(self, name, t, x, q):
        return np.array(self.functions.h[name](t, x, self.u, self.p, q)).ravel()

    # ---------------------------------------------------------------- steps
    def predict(self, t: float, dt: float) -> None:
        noise = self.process_noise(t, dt)
        if self.family == "ekf":
            F = np.array(self.propagation.jac_fd(t, dt, self.x, self.u, self.p))
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
            y, S, K, H, x_new = self._gauss_newton(z, name, t, q, mask, R, self.x)
            x_i, count, tol = self.x, self.functions.config.get("ekf_iterations", 1), self.functions.config.get(
                "ekf_iteration_tolerance", 0.0)
            for _ in range(count - 1):         # Bell & Cathey 1993 (codegen/families/iterated.py)
                if not np.any(np.abs(x_new - x_i) > tol * np.sqrt(np.diag(self.P))):
                    break
                x_i = x_new
                _, _, K, H, x_new = self._gauss_newton(z, name, t, q, mask, R, x_i)
            I_KH = np.eye(len(self.x)) - K @ H
            self.x = x_new
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

    def _gauss_newton(self, z, name, t, q, mask, R, x_i):
        """One linearisation at x_i: y, S, K, H and x- + K (z - h(x_i) - H (x- - x_i))."""
        z_pred = self._h(name, t, x_i, q)
        H = mask[:, None] * np.array(self.functions.jac_h[name](t, x_i, self.u, self.p, q))
        y = self.innovation(z, z_pred, mask, self.wrap[name])
        S = _sym(H @ self.P @ H.T + R)
        K = cho_solve(cho_factor(S, lower=True), H @ self.P).T
        return y, S, K, H, self.x + K @ (y - H @ (self.x - x_i))

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

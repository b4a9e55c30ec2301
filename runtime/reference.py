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
                 kappa: float = 0.0, **overrides):
        if family not in ("ekf", "ukf"):
            raise ValueError("family: expected 'ekf' or 'ukf'")
        model = get_model(model_name)
        self.functions = ModelFunctions(model, make_config(model_name, **overrides))
        self.propagation = self.functions.for_filter(family)     # the family's discretisation
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


# ---------------------------------------------------------------------- manifold filters
def hamilton(p, q) -> np.ndarray:
    """Hamilton product p ⊗ q of scalar-last quaternions (as ``models/quaternion.hamilton``)."""
    pv, pw, qv, qw = p[:3], p[3], q[:3], q[3]
    return np.r_[pw * qv + qw * pv + np.cross(pv, qv), pw * qw - pv @ qv]


def left_matrix(p) -> np.ndarray:
    """L(p) with p ⊗ q = L(p) q (scalar-last)."""
    return np.column_stack([hamilton(p, e) for e in np.eye(4)])


def conjugate(q) -> np.ndarray:
    return q * np.array([-1.0, -1.0, -1.0, 1.0])


def exp_rotvec(theta) -> np.ndarray:
    """Unit quaternion of a rotation vector (rad): [sin(|θ|/2) θ/|θ|; cos(|θ|/2)]."""
    theta = np.asarray(theta, dtype=float)
    angle = np.linalg.norm(theta)
    if angle < 1e-4:
        t2 = angle**2
        return np.r_[(0.5 - t2 / 48 + t2**2 / 3840) * theta, 1 - t2 / 8 + t2**2 / 384]
    return np.r_[np.sin(angle / 2) / angle * theta, np.cos(angle / 2)]


def log_quaternion(q) -> np.ndarray:
    """Rotation vector (rad, shorter rotation) of a unit quaternion."""
    q = q if q[3] >= 0 else -q
    s = np.linalg.norm(q[:3])
    return (2 / q[3] * (1 - s**2 / (3 * q[3]**2)) if s < 1e-4 else 2 * np.arctan2(s, q[3]) / s) * q[:3]


class ManifoldReference:
    """The multiplicative EKF ("mekf") and manifold UKF ("mukf") of ``codegen/families/manifold.py``
    in plain NumPy: the chart x ⊞ δ (q ⊗ Exp(δθ)), x ⊟ x̂ (Log(q̂⁻¹ ⊗ q)) and every Jacobian of it
    written out by hand here (chain rule through the model's CasADi f_d, ∂f_d/∂x, h, ∂h/∂x), the
    quaternion mean by ``numpy.linalg.eigh``. Compiled and reference must agree to round-off."""

    def __init__(self, model, family: str, x0, P0, Q, R: dict | None = None, p=None, kappa: float = 0.0):
        if family not in ("mekf", "mukf"):
            raise ValueError("family: expected 'mekf' or 'mukf'")
        from symkf.models import get_model
        model = get_model(model)
        self.functions = ModelFunctions(model, make_config(model))
        self.family, self.kappa = family, float(kappa)
        self.quaternions = [(qs.index, qs.error_index) for qs in model.quaternions]
        inside = {i + k for i, _ in self.quaternions for k in range(4)}
        self.ordinary = [(i, i - sum(1 for qi, _ in self.quaternions if qi < i))
                         for i in range(model.nx) if i not in inside]
        self.n, self.ne = model.nx, model.n_error
        self.x, self.P, self.Q = np.array(x0, float), np.array(P0, float), np.array(Q, float)
        self.p = np.array(model.param_defaults if p is None else p, float)
        self.u = np.zeros(len(model.inputs))
        self.wrap = {name: np.array(m.wrap) for name, m in model.measurements.items()}
        self.R = {name: np.diag(m.sigma**2) for name, m in model.measurements.items()}
        self.R.update(R or {})
        self.y = self.S = None

    # ---------------------------------------------------------------- the chart
    def retract(self, x, delta):
        out = x.copy()
        for i, e in self.quaternions:
            q = hamilton(x[i:i + 4], exp_rotvec(delta[e:e + 3]))
            out[i:i + 4] = q / np.linalg.norm(q)
        for i, e in self.ordinary:
            out[i] = x[i] + delta[e]
        return out

    def local(self, x, x_ref):
        delta = np.zeros(self.ne)
        for i, e in self.quaternions:
            q, q_ref = x[i:i + 4] / np.linalg.norm(x[i:i + 4]), x_ref[i:i + 4] / np.linalg.norm(x_ref[i:i + 4])
            delta[e:e + 3] = log_quaternion(hamilton(conjugate(q_ref), q))
        for i, e in self.ordinary:
            delta[e] = x[i] - x_ref[i]
        return delta

    def project(self, x):
        out = x.copy()
        for i, _ in self.quaternions:
            out[i:i + 4] = x[i:i + 4] / np.linalg.norm(x[i:i + 4])
        return out

    def retract_jacobian(self, x):
        """∂(x ⊞ δ)/∂δ at δ = 0 (n x n_e): ½ L(q̂)[:, :3] per quaternion, identity otherwise."""
        J = np.zeros((self.n, self.ne))
        for i, e in self.quaternions:
            J[i:i + 4, e:e + 3] = 0.5 * left_matrix(x[i:i + 4])[:, :3]
        for i, e in self.ordinary:
            J[i, e] = 1.0
        return J

    def local_jacobian(self, x_ref, x=None):
        """∂(x ⊟ x_ref)/∂x at x (default x_ref; n_e x n): 2 L(q_ref⁻¹)[:3] (I - n nᵀ)/|q| per quaternion."""
        x = x_ref if x is None else x
        J = np.zeros((self.ne, self.n))
        for i, e in self.quaternions:
            q = x[i:i + 4]
            n = q / np.linalg.norm(q)
            J[e:e + 3, i:i + 4] = 2 * left_matrix(conjugate(x_ref[i:i + 4]))[:3] @ (np.eye(4) - np.outer(n, n)) \
                / np.linalg.norm(q)
        for i, e in self.ordinary:
            J[e, i] = 1.0
        return J

    # ---------------------------------------------------------------- model calls
    def _fd(self, t, dt, x):
        return np.array(self.functions.fd(t, dt, x, self.u, self.p)).ravel()

    def _h(self, name, t, x, q):
        return np.array(self.functions.h[name](t, x, self.u, self.p, q)).ravel()

    def process_noise(self, t, dt):
        if self.functions.noise_gain is None:
            return self.Q * dt
        G = self.local_jacobian(self.x) @ np.array(self.functions.noise_gain(t, self.x, self.u, self.p))
        return G @ self.Q @ G.T * dt

    # ---------------------------------------------------------------- steps
    def predict(self, t: float, dt: float, u=None) -> None:
        if u is not None:
            self.u = np.array(u, float)
        noise = self.process_noise(t, dt)
        if self.family == "mekf":
            x_f = self._fd(t, dt, self.x)
            x_next = self.project(x_f)
            F_state = np.array(self.functions.jac_fd(t, dt, self.x, self.u, self.p))
            F = self.local_jacobian(x_next, x_f) @ F_state @ self.retract_jacobian(self.x)
            self.x, self.P = x_next, _sym(F @ self.P @ F.T + noise)
            return
        offsets, weights = self._sigma_offsets()
        propagated = [self.project(self._fd(t, dt, self.retract(self.x, d))) for d in offsets]
        mean = self.mean(propagated, weights)
        residuals = [self.local(pt, mean) for pt in propagated]
        self.x = mean
        self.P = _sym(sum(w * np.outer(r, r) for w, r in zip(weights, residuals)) + noise)

    def update(self, z, name: str, t: float, q=(), mask=None) -> None:
        z = np.asarray(z, float)
        mask = np.ones_like(z) if mask is None else np.asarray(mask, float)
        R = ReferenceFilter.masked_noise(self.R[name], mask)
        wrap = self.wrap[name]
        if self.family == "mekf":
            z_pred = self._h(name, t, self.x, q)
            H = np.array(self.functions.jac_h[name](t, self.x, self.u, self.p, q)) @ self.retract_jacobian(self.x)
            H = mask[:, None] * H
            y = ReferenceFilter.innovation(z, z_pred, mask, wrap)
            S = _sym(H @ self.P @ H.T + R)
            K = cho_solve(cho_factor(S, lower=True), H @ self.P).T
            I_KH = np.eye(self.ne) - K @ H
            self.x = self.retract(self.x, K @ y)
            self.P = _sym(I_KH @ self.P @ I_KH.T + K @ R @ K.T)
        else:
            offsets, weights = self._sigma_offsets()
            predicted = [self._h(name, t, self.retract(self.x, d), q) for d in offsets]
            ref = predicted[0]
            z_pred = ref + sum(w * np.where(wrap, wrap_angle(zi - ref), zi - ref) for w, zi in zip(weights, predicted))
            dz = [mask * np.where(wrap, wrap_angle(zi - z_pred), zi - z_pred) for zi in predicted]
            S = _sym(sum(w * np.outer(d, d) for w, d in zip(weights, dz)) + R)
            Pxz = sum(w * np.outer(a, b) for w, a, b in zip(weights, offsets, dz))
            K = np.linalg.solve(S, Pxz.T).T
            y = ReferenceFilter.innovation(z, z_pred, mask, wrap)
            self.x = self.retract(self.x, K @ y)
            self.P = _sym(self.P - K @ S @ K.T)
        self.y, self.S = y, S

    def step(self, t: float, dt: float, z, name: str, q=(), mask=None, u=None) -> None:
        self.predict(t, dt, u)
        self.update(z, name, t + dt, q, mask)

    # ---------------------------------------------------------------- UKF algebra
    def _sigma_offsets(self):
        L = np.linalg.cholesky((self.ne + self.kappa) * self.P)
        offsets = [np.zeros(self.ne)] + [L[:, i] for i in range(self.ne)] + [-L[:, i] for i in range(self.ne)]
        weights = [self.kappa / (self.ne + self.kappa)] + [0.5 / (self.ne + self.kappa)] * (2 * self.ne)
        return offsets, weights

    def mean(self, points, weights):
        """Eigenvector mean per quaternion (largest eigenvalue of Σ W q qᵀ, sign of the first
        point's), weighted mean otherwise."""
        mean = sum(w * pt for w, pt in zip(weights, points))
        for i, _ in self.quaternions:
            M = sum(w * np.outer(pt[i:i + 4], pt[i:i + 4]) for w, pt in zip(weights, points))
            v = np.linalg.eigh(M)[1][:, -1]
            mean[i:i + 4] = v if v @ points[0][i:i + 4] >= 0 else -v
        return mean

"""NumPy references of every generated filter, in one place: the readable oracles (and the
"plain Python" timing column). One per algorithm, each with the compiled filter's shape (``x``,
``P``, ``predict``/``update``/``step``):

- :class:`ReferenceFilter`: EKF (Joseph-form update) and UKF (Julier sigma points, paper 004
  eqs (1)-(3), redrawn for the update), as ``codegen/families/kalman.py`` generates them;
- :class:`NumpyCDEKF`: the continuous-discrete EKF of paper 003 (``codegen/families/cd_ekf.py``);
- :class:`ManifoldReference`: multiplicative EKF / manifold UKF (``codegen/families/manifold.py``);
- :class:`ReferenceAttitudeFilter`: paper 000's MEKF, UKF and augmented UKF written as the paper
  writes them (Shuster product, δp charts, eqs (34)-(53)), the quaternion mean by
  ``numpy.linalg.eigh``; the compiled filters are the generic manifold families
  ("mekf" in ``codegen/families/manifold.py``, "sukf"/"aukf" in ``quaternion_filters.py``)
  with the attitude model's options, so this reference checks that the generic path is paper 000;
- :class:`ReferenceMarg` / :func:`reference_step`: paper 001's gradient-descent filter.

The model is evaluated through CasADi (the same Functions the C code calls); masks and angle
wrapping are identical. Compiled and reference filters agree to round-off on the same inputs
(tests/test_contract.py).
"""
from __future__ import annotations

import casadi as ca
import numpy as np
from scipy.linalg import cho_factor, cho_solve, solve_triangular

from symkf.codegen import make_config
from symkf.codegen.families import manifold as manifold_family
from symkf.codegen.families import quaternion_filters as family
from symkf.codegen.families.cd_ekf import reference_functions
from symkf.codegen.families.gradient_descent import ZERO_NORM, marg_functions
from symkf.codegen.kernels import ModelFunctions
from symkf.codegen.spec import STATUS_DOMAIN, STATUS_NONFINITE, STATUS_NOT_PD
from symkf.models import attitude as model
from symkf.models import get_model
from symkf.models import quaternion as quat
from symkf.models.marg import ALPHA_DEFAULT, BETA_MADGWICK
from .backends import SymkfError
from .contract import as_array, covariance


def wrap_angle(a):
    """Wrap to (-pi, pi], the same formula as the generated code (codegen.linalg.wrap_angle)."""
    return a - 2 * np.pi * np.ceil((a - np.pi) / (2 * np.pi))



def _init_filter_state(ref, model, x0, P0, Q, p, R) -> None:
    """The state every Kalman-type reference starts from: x, P, Q, parameters, inputs, per
    measurement its wrap flags and R (default diag(sigma^2)), no innovation yet."""
    ref.x, ref.P, ref.Q = np.array(x0, float), np.array(P0, float), np.array(Q, float)
    ref.p = np.array(model.param_defaults if p is None else p, float)
    ref.u = np.zeros(len(model.inputs))
    ref.wrap = {name: np.array(m.wrap) for name, m in model.measurements.items()}
    ref.R = {name: np.diag(m.sigma**2) for name, m in model.measurements.items()}
    ref.R.update(R or {})
    ref.y = ref.S = None

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


def right_matrix(p) -> np.ndarray:
    """R(p) with q ⊗ p = R(p) q (scalar-last)."""
    return np.column_stack([hamilton(e, p) for e in np.eye(4)])


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
    quaternion mean by ``numpy.linalg.eigh``. Compiled and reference must agree to round-off.
    ``side="left"``: the reference-frame error of ``manifold_side="left"``, Exp(δθ) ⊗ q and
    Log(q ⊗ q_ref⁻¹). ``transition``: the MEKF's F, "step" (through f_d) or "series"
    (I + A dt + (A dt)²/2 of the error dynamics, :meth:`error_rate_matrix`); default the model's
    ``manifold_transition`` (``Model.codegen_defaults``), as the compiled filter."""

    def __init__(self, model, family: str, x0, P0, Q, R: dict | None = None, p=None, kappa: float = 0.0,
                 side: str = "right", transition: str | None = None):
        if family not in ("mekf", "mukf"):
            raise ValueError("family: expected 'mekf' or 'mukf'")
        if side not in ("right", "left"):
            raise ValueError("side: expected 'right' or 'left'")
        from symkf.models import get_model
        model = get_model(model)
        transition = model.codegen_defaults.get("manifold_transition", "step") if transition is None else transition
        if transition not in ("step", "series"):
            raise ValueError("transition: expected 'step' or 'series'")
        self.side, self.transition = side, transition
        self.functions = ModelFunctions(model, make_config(model))
        self._f, self._jac_f = manifold_family.continuous_functions(model)
        self.family, self.kappa = family, float(kappa)
        self.quaternions = [(qs.index, qs.error_index) for qs in model.quaternions]
        inside = {i + k for i, _ in self.quaternions for k in range(4)}
        self.ordinary = [(i, i - sum(1 for qi, _ in self.quaternions if qi < i))
                         for i in range(model.nx) if i not in inside]
        self.n, self.ne = model.nx, model.n_error
        _init_filter_state(self, model, x0, P0, Q, p, R)

    # ---------------------------------------------------------------- the chart
    def retract(self, x, delta):
        out = x.copy()
        for i, e in self.quaternions:
            q = self._compose(x[i:i + 4], exp_rotvec(delta[e:e + 3]))
            out[i:i + 4] = q / np.linalg.norm(q)
        for i, e in self.ordinary:
            out[i] = x[i] + delta[e]
        return out

    def local(self, x, x_ref):
        delta = np.zeros(self.ne)
        for i, e in self.quaternions:
            q, q_ref = x[i:i + 4] / np.linalg.norm(x[i:i + 4]), x_ref[i:i + 4] / np.linalg.norm(x_ref[i:i + 4])
            error = hamilton(conjugate(q_ref), q) if self.side == "right" else hamilton(q, conjugate(q_ref))
            delta[e:e + 3] = log_quaternion(error)
        for i, e in self.ordinary:
            delta[e] = x[i] - x_ref[i]
        return delta

    def _compose(self, q, delta_q):
        """q ⊗ δq (right) or δq ⊗ q (left)."""
        return hamilton(q, delta_q) if self.side == "right" else hamilton(delta_q, q)

    def _product_matrix(self, q):
        """The matrix of δq -> q ⊗ δq (right) or δq ⊗ q (left)."""
        return left_matrix(q) if self.side == "right" else right_matrix(q)

    def project(self, x):
        out = x.copy()
        for i, _ in self.quaternions:
            out[i:i + 4] = x[i:i + 4] / np.linalg.norm(x[i:i + 4])
        return out

    def retract_jacobian(self, x):
        """∂(x ⊞ δ)/∂δ at δ = 0 (n x n_e): ½ L(q̂)[:, :3] (right; ½ R(q̂)[:, :3] left) per
        quaternion, identity otherwise."""
        J = np.zeros((self.n, self.ne))
        for i, e in self.quaternions:
            J[i:i + 4, e:e + 3] = 0.5 * self._product_matrix(x[i:i + 4])[:, :3]
        for i, e in self.ordinary:
            J[i, e] = 1.0
        return J

    def local_jacobian(self, x_ref, x=None):
        """∂(x ⊟ x_ref)/∂x at x (default x_ref; n_e x n): 2 L(q_ref⁻¹)[:3] (I - n nᵀ)/|q| per quaternion
        (R(q_ref⁻¹) for the left side)."""
        x = x_ref if x is None else x
        J = np.zeros((self.ne, self.n))
        for i, e in self.quaternions:
            q = x[i:i + 4]
            n = q / np.linalg.norm(q)
            inverse = self._product_matrix(conjugate(x_ref[i:i + 4]))
            J[e:e + 3, i:i + 4] = 2 * inverse[:3] @ (np.eye(4) - np.outer(n, n)) / np.linalg.norm(q)
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

    def error_rate_matrix(self, t: float) -> np.ndarray:
        """A = ∂δ̇/∂δ at x̂ by the chain rule: ∂(x ⊟ x̂)/∂x · ∂f/∂x · ∂(x̂ ⊞ δ)/∂δ, plus per quaternion
        the motion of the reference point, δ = 2 vec(q̂⁻¹ ⊗ q) moving with q̂: L(q̂̇* ⊗ q̂) (right;
        R(q̂ ⊗ q̂̇*) left), upper-left 3 x 3."""
        x = self.x
        A = self.local_jacobian(x) @ np.array(self._jac_f(t, x, self.u, self.p)) @ self.retract_jacobian(x)
        rate = np.array(self._f(t, x, self.u, self.p)).ravel()
        for i, e in self.quaternions:
            q, q_dot = x[i:i + 4], conjugate(rate[i:i + 4])
            moving = left_matrix(hamilton(q_dot, q)) if self.side == "right" else right_matrix(hamilton(q, q_dot))
            A[e:e + 3, e:e + 3] += moving[:3, :3]
        return A

    # ---------------------------------------------------------------- steps
    def predict(self, t: float, dt: float, u=None) -> None:
        if u is not None:
            self.u = np.array(u, float)
        noise = self.process_noise(t, dt)
        if self.family == "mekf":
            x_f = self._fd(t, dt, self.x)
            x_next = self.project(x_f)
            if self.transition == "series":
                Adt = self.error_rate_matrix(t) * dt
                F = np.eye(self.ne) + Adt + 0.5 * Adt @ Adt
            else:
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
            self.x = self.retract(self.x, K @ y)
            self.P = _sym(self.P - K @ S @ K.T)
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


# ---------------------------------------------------------------------- attitude filters (paper 000)
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


# ---------------------------------------------------------------------- gradient-descent MARG filter (paper 001)
def _call(function: ca.Function, *args) -> np.ndarray:
    return np.asarray(function(*args)).ravel()


def _unit_or_zero(v: np.ndarray) -> tuple[np.ndarray, bool]:
    largest = np.max(np.abs(v))
    scaled = v / largest if largest > 0 else v
    norm = np.linalg.norm(scaled)
    return (scaled / norm, True) if largest * norm > ZERO_NORM else (np.zeros(3), False)


def reference_direction(q: np.ndarray, acc: np.ndarray, mag: np.ndarray | None) -> np.ndarray:
    """Eq (27) normalised, in NumPy around the model's CasADi gradients; zero when not correctable."""
    fns = marg_functions()
    a, acc_ok = _unit_or_zero(acc)
    m, mag_ok = _unit_or_zero(mag) if mag is not None else (np.zeros(3), False)
    if mag_ok:
        b = _call(fns["earth_field_reference"], q, m)
    if acc_ok and mag_ok:
        grad = _call(fns["gradient_stacked"], q, a, b, m)
    elif acc_ok:
        grad = _call(fns["gradient_gravity"], q, a)
    elif mag_ok:
        grad = _call(fns["gradient_earth_field"], q, b, m)
    else:
        return np.zeros(4)
    norm = np.linalg.norm(grad)
    return grad / norm if norm > ZERO_NORM else np.zeros(4)


def reference_step(form: str, q: np.ndarray, dt: float, gyro, acc, mag, beta: float, alpha: float) -> np.ndarray:
    """One step of (26)-(30) or (31) in NumPy (the model's equations evaluated by CasADi)."""
    q_dot = _call(marg_functions()["quaternion_rate"], q, gyro)        # (7)-(8)
    direction = reference_direction(q, np.asarray(acc, float), None if mag is None else np.asarray(mag, float))
    if form == "simple":
        q_est = q + (q_dot - beta * direction) * dt                    # (31)
    else:
        rate_nabla = alpha * np.linalg.norm(q_dot)                     # μ_t/Δt (28)
        corrected = bool(direction.any()) and rate_nabla + beta > 0
        gamma = beta / (rate_nabla + beta) if corrected else 0.0       # (30)
        q_est = gamma * (q - rate_nabla * dt * direction) + (1 - gamma) * (q + q_dot * dt)   # (26), (9), (29)
    return q_est / np.linalg.norm(q_est)


def reference_run(form: str, mode: str, q0, dt, gyro, acc, mag=None, beta: float = BETA_MADGWICK,
                  alpha: float = ALPHA_DEFAULT) -> np.ndarray:
    """The NumPy reference over N samples: (N, 4) estimates, the same contract as :meth:`MargFilter.run`."""
    q = np.asarray(q0, dtype=float).copy()
    out = np.zeros((len(dt), 4))
    for k in range(len(dt)):
        q = reference_step(form, q, dt[k], gyro[k], acc[k], mag[k] if mode == "marg" else None, beta, alpha)
        out[k] = q
    return out


def reference_initial(acc, mag) -> np.ndarray:
    """Initial orientation (TRIAD, 9-axis) via the model's CasADi function."""
    return _call(marg_functions()["initial_orientation"], acc, mag)


class ReferenceMarg:
    """NumPy reference of :class:`~symkf.runtime.marg.MargFilter`: state ``x`` = q, ``step`` per sample."""

    def __init__(self, form: str, mode: str, q0, beta: float = BETA_MADGWICK, alpha: float = ALPHA_DEFAULT):
        self.form, self.mode, self.beta, self.alpha = form, mode, beta, alpha
        self.x = np.asarray(q0, dtype=float).copy()

    def step(self, dt: float, gyro, acc, mag=None) -> np.ndarray:
        self.x = reference_step(self.form, self.x, dt, gyro, acc, mag if self.mode == "marg" else None,
                                self.beta, self.alpha)
        return self.x

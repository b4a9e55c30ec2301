"""NumPy reference of the multiplicative EKF and the manifold UKF (``codegen/families/mekf.py``, ``mukf.py``),
with the quaternion algebra it needs written out in NumPy (Hamilton product, scalar-last)."""
from __future__ import annotations

import numpy as np
from scipy.linalg import cho_factor, cho_solve

from symkf.codegen import make_config
from symkf.codegen.families import manifold as manifold_family
from symkf.codegen.model_functions import ModelFunctions
from symkf.models import get_model
from .common import _init_filter_state, _sym, wrap_angle
from .kalman import ReferenceFilter


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
    ``manifold_transition`` (``Model.codegen_defaults``), as the compiled filter. ``iterations``,
    ``iteration_tolerance``: the MEKF's iterated update (codegen options ``mekf_iterations``,
    ``mekf_iteration_tolerance``; default the model's, else 1 and 0), :meth:`iterated_correction`."""

    def __init__(self, model, family: str, x0, P0, Q, R: dict | None = None, p=None, kappa: float = 0.0,
                 side: str = "right", transition: str | None = None, iterations: int | None = None,
                 iteration_tolerance: float | None = None):
        if family not in ("mekf", "mukf"):
            raise ValueError("family: expected 'mekf' or 'mukf'")
        if side not in ("right", "left"):
            raise ValueError("side: expected 'right' or 'left'")
        model = get_model(model)
        transition = model.codegen_defaults.get("manifold_transition", "step") if transition is None else transition
        if transition not in ("step", "series"):
            raise ValueError("transition: expected 'step' or 'series'")
        self.side, self.transition = side, transition
        defaults = model.codegen_defaults
        self.iterations = int(defaults.get("mekf_iterations", 1) if iterations is None else iterations)
        self.iteration_tolerance = float(defaults.get("mekf_iteration_tolerance", 0.0) if iteration_tolerance is None
                                         else iteration_tolerance)
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

    def mekf_transition(self, t: float, dt: float):
        """The MEKF's x̂⁻ = f_d(x̂) projected and its error-state F (the smoother's too)."""
        x_f = self._fd(t, dt, self.x)
        x_next = self.project(x_f)
        if self.transition == "series":
            Adt = self.error_rate_matrix(t) * dt
            return x_next, np.eye(self.ne) + Adt + 0.5 * Adt @ Adt
        F_state = np.array(self.functions.jac_fd(t, dt, self.x, self.u, self.p))
        return x_next, self.local_jacobian(x_next, x_f) @ F_state @ self.retract_jacobian(self.x)

    # ---------------------------------------------------------------- steps
    def predict(self, t: float, dt: float, u=None) -> None:
        if u is not None:
            self.u = np.array(u, float)
        noise = self.process_noise(t, dt)
        if self.family == "mekf":
            x_next, F = self.mekf_transition(t, dt)
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
            delta, P, y, S = self._linearised(z, name, t, q, mask, R, self.x, np.zeros(self.ne))
            if self.iterations > 1:
                delta, P = self.iterated_correction(z, name, t, q, mask, R, delta, P)
            self.x, self.P = self.retract(self.x, delta), P
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

    def _linearised(self, z, name, t, q, mask, R, x_i, delta):
        """One Gauss-Newton step at x_i = x (+) delta: K (y_i + H_i delta), P - K S K^T, y_i, S_i."""
        H = mask[:, None] * (np.array(self.functions.jac_h[name](t, x_i, self.u, self.p, q)) @ self.retract_jacobian(x_i))
        y = ReferenceFilter.innovation(z, self._h(name, t, x_i, q), mask, self.wrap[name])
        S = _sym(H @ self.P @ H.T + R)
        K = cho_solve(cho_factor(S, lower=True), H @ self.P).T
        return K @ (y + H @ delta), _sym(self.P - K @ S @ K.T), y, S

    def iterated_correction(self, z, name, t, q, mask, R, delta, P):
        """The MEKF's Gauss-Newton iterations (``mekf.iterated_correction``): relinearised at
        x (+) delta_i until delta moves by no more than the tolerance in prior sigmas."""
        diagonal = np.diag(self.P)
        sigma = np.sqrt(np.where(diagonal > 0, diagonal, 1.0))
        previous = np.zeros(self.ne)
        for _ in range(self.iterations - 1):
            if not np.any(np.abs(delta - previous) > self.iteration_tolerance * sigma):
                break
            previous = delta
            delta, P, _, _ = self._linearised(z, name, t, q, mask, R, self.retract(self.x, delta), delta)
        return delta, P

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

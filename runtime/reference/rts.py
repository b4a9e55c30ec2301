"""NumPy references of the fixed-interval smoothers (codegen/families/rts.py), in textbook form.

- :func:`ekf_forward` + :func:`rts`: the EKF run step by step with its predictions recorded
  (x^-_k, P^-_k and F_k of every step), then the classic Rauch–Tung–Striebel backward pass over
  them, G_k = P_k F_{k+1}^T (P^-_{k+1})^-1 (Rauch, Tung & Striebel 1965). The generated smoother
  recomputes those predictions from the filtered rows instead; both agree to round-off.
- :func:`ukf_rts`: the unscented RTS smoother (Särkkä 2008) over a run's filtered rows, sigma
  points of (x_k, P_k) propagated over step k + 1.
- :func:`mekf_rts`: the error-state RTS smoother of the multiplicative EKF over a run's filtered
  rows, with the NumPy reference's chart and F (runtime/reference/manifold.py):
  x^s_k = x_k ⊞ G (x^s_{k+1} ⊟ x^-), G = P_k Fᵀ (P^-)^-1.
- :func:`cd_ekf_rts`: the continuous-discrete EKF's RTS smoother over a run's filtered rows, with
  the NumPy reference's time update (runtime/reference/cd_ekf.py): x^-, P^- and the transition
  matrix Phi integrated together by RK4, G = P_k Phiᵀ (P^-)^-1.

Both take the run's convention: step k predicts from t[k] over dt[k], then updates; a step whose
update is skipped (``updated[k]`` False: masked, gated) is a prediction.
"""
from __future__ import annotations

import numpy as np
from scipy.linalg import cho_factor, cho_solve

from .common import _sym


def ekf_forward(ref, t, dt, z, name: str, q, mask, u=None, updated=None) -> dict[str, np.ndarray]:
    """An EKF run of the reference filter ``ref`` (a :class:`ReferenceFilter` of family "ekf"),
    recording per step x^-, P^-, F and the filtered x, P. ``updated[k]`` False skips step k's
    update (as the compiled filter's gate did); ``u``: (N, nu) inputs or None."""
    n_steps = len(dt)
    out = {key: [] for key in ("x_pred", "P_pred", "F", "x", "P")}
    for k in range(n_steps):
        if u is not None:
            ref.u = np.asarray(u[k], float)
        F = np.array(ref.propagation.jac_fd(t[k], dt[k], ref.x, ref.u, ref.p))
        ref.predict(t[k], dt[k])
        out["x_pred"].append(ref.x.copy())
        out["P_pred"].append(ref.P.copy())
        out["F"].append(F)
        if updated is None or updated[k]:
            ref.update(z[k], name, t[k] + dt[k], q[k], mask[k])
        out["x"].append(ref.x.copy())
        out["P"].append(ref.P.copy())
    return {key: np.array(value) for key, value in out.items()}


def rts(x, P, x_pred, P_pred, F) -> tuple[np.ndarray, np.ndarray]:
    """The RTS backward pass over filtered (x, P) and recorded predictions (x^-, P^-, F) of each step."""
    xs, Ps = x.copy(), P.copy()
    for k in range(len(x) - 2, -1, -1):
        G = cho_solve(cho_factor(P_pred[k + 1], lower=True), F[k + 1] @ P[k]).T     # P F^T (P^-)^-1
        xs[k] = x[k] + G @ (xs[k + 1] - x_pred[k + 1])
        Ps[k] = _sym(P[k] + G @ (Ps[k + 1] - P_pred[k + 1]) @ G.T)
    return xs, Ps


def ukf_rts(ref, x, P, t, dt, u=None) -> tuple[np.ndarray, np.ndarray]:
    """Särkkä's unscented RTS smoother over filtered (x, P), with the reference UKF ``ref``'s sigma
    points (Julier, its kappa), f_d and process noise; step k + 1 propagates row k."""
    xs, Ps = x.copy(), P.copy()
    for k in range(len(x) - 2, -1, -1):
        if u is not None:
            ref.u = np.asarray(u[k + 1], float)
        ref.x = x[k]
        points, weights = ref._sigma_points(x[k], P[k])
        moved = [ref._fd(t[k + 1], dt[k + 1], pt) for pt in points]
        x_pred = sum(w * m for w, m in zip(weights, moved))
        P_pred = sum(w * np.outer(m - x_pred, m - x_pred) for w, m in zip(weights, moved)) + \
            ref.process_noise(t[k + 1], dt[k + 1])
        D = sum(w * np.outer(pt - x[k], m - x_pred) for w, pt, m in zip(weights, points, moved))
        G = D @ np.linalg.inv(P_pred)
        xs[k] = x[k] + G @ (xs[k + 1] - x_pred)
        Ps[k] = _sym(P[k] + G @ (Ps[k + 1] - P_pred) @ G.T)
    return xs, Ps


def mekf_rts(ref, x, P, t, dt, u=None) -> tuple[np.ndarray, np.ndarray]:
    """The MEKF's error-state RTS smoother over filtered (x, P) with the reference ``ref`` (a
    :class:`ManifoldReference` of family "mekf"): its transition, process noise and chart."""
    xs, Ps = x.copy(), P.copy()
    for k in range(len(x) - 2, -1, -1):
        if u is not None:
            ref.u = np.asarray(u[k + 1], float)
        ref.x = x[k]
        x_pred, F = ref.mekf_transition(t[k + 1], dt[k + 1])
        P_pred = _sym(F @ P[k] @ F.T + ref.process_noise(t[k + 1], dt[k + 1]))
        G = cho_solve(cho_factor(P_pred, lower=True), F @ P[k]).T
        xs[k] = ref.retract(x[k], G @ ref.local(xs[k + 1], x_pred))
        Ps[k] = _sym(P[k] + G @ (Ps[k + 1] - P_pred) @ G.T)
    return xs, Ps


def cd_ekf_rts(ref, x, P, t, dt, u=None) -> tuple[np.ndarray, np.ndarray]:
    """The continuous-discrete RTS smoother over filtered (x, P) with the reference ``ref`` (a
    :class:`NumpyCDEKF`): step k + 1 integrates row k to x^-, P^- and Phi (the same RK4)."""
    xs, Ps = x.copy(), P.copy()
    for k in range(len(x) - 2, -1, -1):
        x_pred, P_pred, Phi = ref.transition(t[k + 1], dt[k + 1], x[k], P[k], None if u is None else u[k + 1])
        G = cho_solve(cho_factor(P_pred, lower=True), Phi @ P[k]).T          # P Phi^T (P^-)^-1
        xs[k] = x[k] + G @ (xs[k + 1] - x_pred)
        Ps[k] = _sym(P[k] + G @ (Ps[k + 1] - P_pred) @ G.T)
    return xs, Ps

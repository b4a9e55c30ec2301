"""Square-root EKF, family ``"srekf"``: the EKF of ``kalman.py`` carrying the lower Cholesky
factor L of the covariance (P = L L^T), in the array form (Kailath, Sayed & Hassibi, Linear
Estimation, 2000, sec. 12.3; Morf & Kailath 1975): every covariance is a triangularisation (QR)
of a pre-array, never a difference of products, so it stays positive semi-definite by
construction, also in single precision.

- prediction: x- = f_d(x), L- = qr[F L, sqrt(Q_d)] with sqrt(Q_d) = sqrt(dt) chol(Q), or
  sqrt(dt) G chol(Q) (G = df/dw at the step start) for a model with noise(): P- = F P F^T + Q_d;
- update: the pre-array [[chol(R), H L], [0, L]] triangularised to [[S^1/2, 0], [K_b, L+]]:
  S = S^1/2 S^1/2^T = H P H^T + R, K = K_b S^-1/2, x+ = x- + K_b S^-1/2 y and
  L+ L+^T = P - P H^T S^-1 H P, which equals the Joseph form of the EKF in exact arithmetic.

Masks, gates and status codes are those of ``framework.py``; the carried factor as in
``srukf.py`` (lower triangle read, written with 0 above the diagonal and a diagonal >= 0).
"""
from __future__ import annotations

import casadi as ca

from symkf.models.base import Model
from .. import linalg, square_root
from ..model_functions import ModelFunctions, Symbols
from ..spec import Family
from .framework import compose_step, filter_spec, innovation, make_kernel, masked_noise, register_family, update_outputs
from .kalman import UPDATE_INPUTS, _predict_doc, noise_symbols, predict_status
from .srukf import factor_arg, factor_inputs_finite, noise_factor


def srekf_predict_expr(symbols: Symbols, fns: ModelFunctions, x, L, t, dt, Q):
    s = symbols.sym
    x_next, F = fns.for_filter("srekf").fd_and_jac(t, dt, x, s["u"], s["p"])
    noise, ok_q = noise_factor(symbols, fns, Q, x, t, dt)
    L_pred = square_root.triangularize(ca.horzcat(F @ L, noise))
    return x_next, L_pred, ok_q * square_root.factor_flag(L)


def srekf_update_expr(symbols: Symbols, fns: ModelFunctions, name: str, msym: dict, wrap, x, L, t):
    s = symbols.sym
    n = x.shape[0]
    z_pred, H_full = fns.h_and_jac[name](t, x, s["u"], s["p"], msym["q"])
    mask = msym["mask"]
    m = mask.shape[0]
    H = ca.diag(mask) @ H_full
    R_root, ok_r = linalg.cholesky(masked_noise(msym["R"], mask))
    pre = ca.vertcat(ca.horzcat(R_root, H @ L), ca.horzcat(ca.SX.zeros(n, m), L))
    post = square_root.triangularize(pre)
    S_z, ok_s = square_root.usable_factor(post[:m, :m])
    K_bar, L_new = post[m:, :m], post[m:, m:]
    y = innovation(msym["z"], z_pred, mask, wrap)
    e = linalg.solve_lower(S_z, y)
    return x + K_bar @ e, L_new, y, square_root.outer_of(S_z), ok_r * ok_s * square_root.factor_flag(L), ca.sumsqr(e)


def srekf_kernels(model: Model, symbols: Symbols, fns: ModelFunctions) -> Family:
    s = symbols.sym
    L = ca.tril(s["P"])                          # only the lower triangle is read
    factor = {"P": factor_arg(model.nx)}
    qsym, qarg = noise_symbols(model)
    Q = qsym.get("Q", s["Q"])
    x_pred, L_pred, ok = srekf_predict_expr(symbols, fns, s["x"], L, s["t"], s["dt"], Q)
    kernels = [make_kernel("srekf_predict", _predict_doc(model, "Square-root EKF", "L = qr[F L, sqrt(Q_d)]"),
                           symbols, qsym, {**qarg, **factor}, ["t", "dt", "x", "P", "u", "p", "Q"],
                           [("x", x_pred), ("P", L_pred), ("status", predict_status(ok))])]
    kernels += array_update_kernels("srekf", "Square-root EKF", model, symbols, fns, kernels[0])
    return Family(kernels, [filter_spec("srekf", "srekf", kernels, model.measurements, covariance="cholesky")])


def array_update_kernels(family: str, title: str, model: Model, symbols: Symbols, fns: ModelFunctions,
                         predict) -> list:
    """``<family>_update_<m>`` (the array-form update of :func:`srekf_update_expr`) and
    ``<family>_step_<m>`` (``predict`` then that update) for every measurement m: the updates of
    every square-root family whose state is ordinary (srekf, srcdekf)."""
    s = symbols.sym
    L, factor = ca.tril(s["P"]), {"P": factor_arg(model.nx)}
    kernels = []
    for name, meas in model.measurements.items():
        msym, marg = symbols.measurement(name)
        upd = srekf_update_expr(symbols, fns, name, msym, meas.wrap, s["x"], L, s["t"])
        update = make_kernel(
            f"{family}_update_{name}", f"{title} update with measurement '{name}' at time t (array form, masked, "
            "gated).", symbols, msym, {**marg, **factor}, UPDATE_INPUTS,
            update_outputs(upd, s["x"], L, msym["gate"], msym["mask"], factor_inputs_finite(symbols, s["P"]), factor=True))
        kernels += [update, compose_step(f"{family}_step_{name}", predict, update)]
    return kernels


register_family("srekf", srekf_kernels)

"""Square-root multiplicative EKF, family ``"srmekf"``: the MEKF of ``mekf.py`` (error state on the
chart of ``chart.py``, multiplicative reset) carrying the lower Cholesky factor L of the
error-state covariance (P = L L^T, n_error x n_error), in the array form of ``srekf.py``
(Kailath, Sayed & Hassibi, Linear Estimation, 2000, sec. 12.3):

- prediction: x- = f_d(x) projected (q / |q|), L- = qr[F L, sqrt(Q_d)] with F the MEKF's
  error-state transition (``ManifoldFunctions.step_and_jac``) and sqrt(Q_d) a square root of the
  MEKF's Q_d (``manifold.error_process_noise``): sqrt(dt) chol(Q) (additive), sqrt(dt) J G chol(Q)
  (the model's noise(), J = d(x (-) x^)/dx), or G_d chol(Q) / sqrt(dt) (held noise): P- = F P F^T + Q_d;
- update: H = dh(x (+) d)/dd at d = 0 (masked rows 0), R in innovation coordinates (D R D^T for
  a measurement with its own noise); the pre-array [[chol(R), H L], [0, L]] triangularised to
  [[S^1/2, 0], [K_b, L+]], d = K_b S^-1/2 y, then the multiplicative reset x+ = x (+) d, with
  the covariance not transported to the reset point (the first-order reset of the MEKF, Lefferts,
  Markley & Shuster 1982). In exact arithmetic these are the MEKF's numbers; the MEKF's
  ``manifold_update="sequential"`` (m scalar updates, the same numbers) has no square-root form
  here: the array form is one triangularisation for any R, so that option changes nothing.

The step kernel is predict then update (``framework.compose_step``); masks, gates, status codes
and the input rules are the manifold filters' (``manifold.py``); the carried factor as in
``srukf.py`` (lower triangle read, written with 0 above the diagonal and a diagonal >= 0).
"""
from __future__ import annotations

import casadi as ca

from symkf.models.base import Model
from .. import linalg, square_root
from ..model_functions import ModelFunctions, Symbols
from ..spec import Arg, Family
from .chart import ManifoldOptions
from .framework import compose_step, filter_spec, make_kernel, masked_noise, register_family
from .kalman import UPDATE_INPUTS
from .manifold import (ManifoldFunctions, ManifoldSymbols, _error_names, chart_innovation, measurement_input,
                       predict_kernel, require_quaternion, update_outputs)
from .mekf import PREDICT_INPUTS, masked_rows
from .srukf import FACTOR_ARG_DESCRIPTION


def error_factor_arg(model: Model) -> Arg:
    """The carried ``P`` of the square-root manifold filter: the factor of the error covariance."""
    ne = model.n_error
    return Arg("P", (ne, ne), "error units", f"{FACTOR_ARG_DESCRIPTION}; error state {_error_names(model)} "
                                             "(rotation vectors in rad)")


def error_noise_factor(mf: ManifoldFunctions, ms: ManifoldSymbols, Q, x, t, dt):
    """A square root C of the MEKF's Q_d (C C^T = Q_d, ``manifold.error_process_noise``) and a 0/1
    flag that Q was positive semi-definite."""
    s = ms.base.sym
    root, ok = square_root.cholesky_psd(Q)
    if mf.options.noise == "held":        # G_d (Q / dt) G_d^T; dt <= 0 is refused by predict_status
        G = mf.held_noise_gain(t, dt, x, s["u"], s["p"])
        return G @ root / ca.sqrt(linalg.guarded(dt, dt > 0)), ok
    root_dt = ca.sqrt(ca.fmax(dt, 0))
    if mf.fns.noise_gain is None:
        return root * root_dt, ok
    G = mf.local_jacobian(x) @ mf.fns.noise_gain(t, x, s["u"], s["p"])
    return G @ root * root_dt, ok


def srmekf_predict_expr(mf: ManifoldFunctions, ms: ManifoldSymbols, L):
    """x- = f_d(x) projected, L- = qr[F L, sqrt(Q_d)] and a 0/1 flag (Q PSD, L a factor)."""
    s = ms.base.sym
    x_pred, F = mf.step_and_jac(s["t"], s["dt"], s["x"], s["u"], s["p"])
    noise, ok_q = error_noise_factor(mf, ms, ms.sym["Q"], s["x"], s["t"], s["dt"])
    return x_pred, square_root.triangularize(ca.horzcat(F @ L, noise)), ok_q * square_root.factor_flag(L)


def srmekf_update_expr(mf: ManifoldFunctions, ms: ManifoldSymbols, name: str, msym: dict, wrap, L):
    """The array-form update of x, L at t, the reset x (+) K y; the tuple of ``manifold.update_outputs``."""
    s = ms.base.sym
    t, x, u, p, q = s["t"], s["x"], s["u"], s["p"], msym["q"]
    m = measurement_input(mf.model, ms, name, msym)
    H = masked_rows(m.mask, mf.jac_h[name](t, x, u, p, q))
    y = chart_innovation(mf, name, m, mf.h_inline[name](t, x, u, p, q), wrap)
    R_root, ok_r = linalg.cholesky(masked_noise(mf.measurement_noise(name, msym["R"], t, x, u, p, q), m.mask))
    k, n = H.shape
    pre = ca.vertcat(ca.horzcat(R_root, H @ L), ca.horzcat(ca.SX.zeros(n, k), L))
    post = square_root.triangularize(pre)
    S_z, ok_s = square_root.usable_factor(post[:k, :k])
    e = linalg.solve_lower(S_z, y)
    correction = post[k:, :k] @ e
    ok = ok_r * ok_s * square_root.factor_flag(L)
    update = (mf.retract(x, correction), post[k:, k:], y, square_root.outer_of(S_z), ok, ca.sumsqr(e), m.finite,
              mf.chart.in_domain(correction))
    return update, m


def srmekf_kernels(model: Model, symbols: Symbols, fns: ModelFunctions) -> Family:
    require_quaternion(model, "srmekf")
    mf, ms = ManifoldFunctions(model, fns), ManifoldSymbols(model, symbols)
    L = ca.tril(ms.sym["P"])                         # only the lower triangle is read
    factor = {"P": error_factor_arg(model)}
    x_pred, L_pred, ok = srmekf_predict_expr(mf, ms, L)
    doc = (f"Square-root multiplicative EKF prediction from t to t + dt (x = f_d(x), |q| = 1; "
           f"L = qr[F L, sqrt(Q_d)] in error coordinates).")
    predict = predict_kernel("srmekf_predict", doc, ms, mf, x_pred, L_pred, ok, PREDICT_INPUTS, extra_arg=factor)
    kernels = [predict]
    for name, meas in model.measurements.items():
        msym, marg = ms.measurement(name)
        upd, m = srmekf_update_expr(mf, ms, name, msym, meas.wrap, L)
        update = make_kernel(
            f"srmekf_update_{name}", f"Square-root multiplicative EKF update with '{name}' at time t (array form: "
            "qr[[chol(R), H L], [0, L]], reset x = x (+) K y; masked, gated).", symbols, msym, {**marg, **factor},
            UPDATE_INPUTS, update_outputs(mf.chart, upd, ms.base.sym["x"], L, msym, m))
        kernels += [update, compose_step(f"srmekf_step_{name}", predict, update)]
    return Family(kernels, [filter_spec("srmekf", "srmekf", kernels, model.measurements, covariance="cholesky")])


register_family("srmekf", srmekf_kernels, quaternions=True, options=(ManifoldOptions,))

"""Square-root UKF, family ``"srukf"``: the UKF of ``kalman.py`` carrying the lower Cholesky
factor L of the covariance (P = L L^T) instead of P (Van der Merwe & Wan, "The square-root
unscented Kalman filter for state and parameter estimation", ICASSP 2001, Algorithm 3.1).

The same estimator as the UKF (Julier sigma points x, x +/- sqrt(n + kappa) L_i, weights
W_0 = kappa/(n + kappa), W_i = 1/(2(n + kappa)); angle components averaged on the circle;
non-additive noise through G = df/dw): the two agree to round-off in double. What differs is
that P is never formed: the factor is made and changed directly,

- prediction: L- = qr{[sqrt(W_1) (Y_1..2n - x-), sqrt(dt) chol(Q) (or G chol(Q))]}, then
  cholupdate(L-, Y_0 - x-, W_0) (a downdate when kappa < 0);
- update: S_z = qr{[sqrt(W_1) (Z_1..2n - z-), chol(R)]} and cholupdate with Z_0 - z-;
  K = P_xz S_z^-T S_z^-1, x+ = x- + K y, L+ = cholupdate(L-, K S_z, -1), m downdates.

A downdate that leaves a matrix that is not positive definite is SYMKF_ERR_NOT_PD with x and L
unchanged; masks, gates and status codes are those of ``framework.py``. The kernels read only
the lower triangle of the carried factor, and write a factor whose upper triangle is 0 and whose
diagonal is >= 0. The Python runtime converts at the boundary: a user gives and reads P
(``Filter.P``) and can read L (``Filter.factor``); the C API carries L in its ``P`` argument.
"""
from __future__ import annotations

import casadi as ca

from symkf.models.base import Model
from .. import linalg, square_root
from ..discretize import measurement_function
from ..model_functions import ModelFunctions, Symbols
from ..spec import STATUS_DOMAIN, Arg, Family
from .framework import (all_finite, compose_step, filter_spec, innovation, make_kernel, masked_noise, register_family,
                        update_outputs)
from .kalman import (UPDATE_INPUTS, _angle_difference, _predict_doc, _weighted_mean, noise_symbols, predict_status,
                     sigma_columns)

#: The carried covariance argument of a square-root family (the C name stays ``P``: one run loop).
FACTOR_ARG_DESCRIPTION = ("lower Cholesky factor L of the state error covariance, P = L L^T (lower triangle "
                          "read; written with 0 above the diagonal and a diagonal >= 0)")


def factor_arg(n: int) -> Arg:
    return Arg("P", (n, n), "state units", FACTOR_ARG_DESCRIPTION)


def noise_factor(symbols: Symbols, fns: ModelFunctions, Q, x, t, dt):
    """A square root of Q_d (n x n or n x nw) and a 0/1 flag that Q was PSD: sqrt(dt) chol(Q),
    or sqrt(dt) G chol(Q) with G = df/dw at the step start for a model with noise()."""
    C, ok = square_root.cholesky_psd(Q)
    root_dt = ca.sqrt(ca.fmax(dt, 0))
    if fns.noise_gain is None:
        return C * root_dt, ok
    G = fns.noise_gain(t, x, symbols.sym["u"], symbols.sym["p"])
    return G @ C * root_dt, ok


def weighted_factor(weights: list, deviations: list[ca.SX], extra: ca.SX):
    """The factor of sum_i W_i d_i d_i^T + extra extra^T, by QR of the columns
    sqrt(W_i) d_i (i >= 1, equal weights) and extra, then a rank-one update (W_0 >= 0) or
    downdate (W_0 < 0) with d_0. Returns the factor and a 0/1 flag (the downdate succeeded)."""
    root = ca.sqrt(ca.fmax(weights[1], 0))
    L = square_root.triangularize(ca.horzcat(*[root * d for d in deviations[1:]], extra))
    w0 = weights[0]
    up, _ = square_root.cholesky_update(L, ca.sqrt(ca.fmax(w0, 0)) * deviations[0], +1)
    down, ok = square_root.cholesky_update(L, ca.sqrt(ca.fmax(-w0, 0)) * deviations[0], -1)
    negative = w0 < 0
    return linalg.select(negative, down, up), 1 - negative + negative * ok


def sigma_scale(kappa: ca.SX, n: int):
    """sqrt(n + kappa), the 2n + 1 weights and the flag n + kappa > 0 (else SYMKF_ERR_DOMAIN)."""
    scale = n + kappa
    positive = scale > 0
    safe = linalg.guarded(scale, positive)
    return ca.sqrt(safe), [kappa / safe] + [0.5 / safe] * (2 * n), positive


def srukf_predict_expr(symbols: Symbols, fns: ModelFunctions, x, L, t, dt, Q):
    """x-, L- and a 0/1 success flag; the sigma points as the UKF's (``kalman.py``)."""
    s = symbols.sym
    n = x.shape[0]
    root, weights, positive = sigma_scale(s["kappa"], n)
    offsets = root * L
    propagation = fns.for_filter("srukf")
    if fns.config.precision == "float":          # increments of x, as the float UKF (kalman.py)
        D = ca.horzcat(ca.SX.zeros(n, 1), offsets, -offsets)
        Y = propagation.increment_columns(2 * n + 1)(t, dt, x, D, s["u"], s["p"])
        moved = [Y[:, i] for i in range(2 * n + 1)]
        mean = _weighted_mean(moved, weights)
        x_pred, deviations = x + mean, [y - mean for y in moved]
    else:
        fd = propagation.fd_at_points("sigma", {"x": ca.SX.sym("x", n), "L": ca.SX.sym("L", ca.Sparsity.lower(n))},
                                      sigma_columns)
        Y = fd(t, dt, x, ca.tril(offsets), s["u"], s["p"])
        moved = [Y[:, i] for i in range(2 * n + 1)]
        x_pred = _weighted_mean(moved, weights)
        deviations = [y - x_pred for y in moved]
    noise, ok_q = noise_factor(symbols, fns, Q, x, t, dt)
    L_pred, ok = weighted_factor(weights, deviations, noise)
    return x_pred, L_pred, ok * ok_q * positive * square_root.factor_flag(L)


def srukf_update_expr(symbols: Symbols, fns: ModelFunctions, name: str, msym: dict, wrap, x, L, t):
    s = symbols.sym
    n = x.shape[0]
    mask = msym["mask"]
    root, weights, positive = sigma_scale(s["kappa"], n)
    offsets = [root * L[:, i] for i in range(n)]
    dx = [ca.SX.zeros(n)] + offsets + [-o for o in offsets]
    h = measurement_function(symbols.model, name)            # inlined: the points share terms (CSE)
    predicted = [h(t, x + d, s["u"], s["p"], msym["q"]) for d in dx]
    z_pred = _weighted_mean(predicted, weights, wrap)
    dz = [mask * _angle_difference(zi, z_pred, wrap) for zi in predicted]
    R_root, ok_r = linalg.cholesky(masked_noise(msym["R"], mask))
    S_z, ok_s = weighted_factor(weights, dz, R_root)
    S_z, ok_pd = square_root.usable_factor(S_z)
    Pxz = sum((w * a @ b.T for w, a, b in zip(weights, dx, dz)), ca.SX.zeros(n, dz[0].shape[0]))
    # K = Pxz S_z^-T S_z^-1; with V = S_z^-1 Pxz^T: K = V^T S_z^-1, U = K S_z = V^T
    V = linalg.solve_lower(S_z, Pxz.T)
    y = innovation(msym["z"], z_pred, mask, wrap)
    e = linalg.solve_lower(S_z, y)
    x_new = x + V.T @ e
    L_new, ok_d = L, ca.SX(1)
    for j in range(V.shape[0]):                              # m downdates by the columns of U = K S_z
        L_new, ok_j = square_root.cholesky_update(L_new, V[j, :].T, -1)
        ok_d = ok_d * ok_j
    S = square_root.outer_of(S_z)
    ok = positive * ok_r * ok_s * ok_pd * ok_d * square_root.factor_flag(L)
    return x_new, L_new, y, S, ok, ca.sumsqr(e)


def factor_inputs_finite(symbols: Symbols, L: ca.SX) -> ca.SX:
    """The update's x and L are finite (as ``kalman.update_inputs_finite``: a fused step's
    predicted state reaches the update without a caller's test)."""
    return all_finite([symbols.sym["x"], L])


def srukf_kernels(model: Model, symbols: Symbols, fns: ModelFunctions) -> Family:
    s = symbols.sym
    n = model.nx
    L = ca.tril(s["P"])                          # only the lower triangle is read
    factor = {"P": factor_arg(n)}
    qsym, qarg = noise_symbols(model)
    Q = qsym.get("Q", s["Q"])
    x_pred, L_pred, ok = srukf_predict_expr(symbols, fns, s["x"], L, s["t"], s["dt"], Q)
    status = linalg.select(s["kappa"] + n > 0, predict_status(ok), STATUS_DOMAIN)
    kernels = [make_kernel("srukf_predict", _predict_doc(model, "Square-root UKF", "QR of the 2n+1 sigma points, "
                                                         "Van der Merwe & Wan 2001"),
                           symbols, qsym, {**qarg, **factor}, ["t", "dt", "x", "P", "u", "p", "Q", "kappa"],
                           [("x", x_pred), ("P", L_pred), ("status", status)])]
    for name, meas in model.measurements.items():
        msym, marg = symbols.measurement(name)
        upd = srukf_update_expr(symbols, fns, name, msym, meas.wrap, s["x"], L, s["t"])
        kernels.append(make_kernel(
            f"srukf_update_{name}", f"Square-root UKF update with measurement '{name}' at time t (QR, m Cholesky "
            "downdates; masked, gated).", symbols, msym, {**marg, **factor}, UPDATE_INPUTS + ["kappa"],
            update_outputs(upd, s["x"], L, msym["gate"], msym["mask"], factor_inputs_finite(symbols, s["P"]), factor=True)))
        kernels.append(compose_step(f"srukf_step_{name}", kernels[0], kernels[-1]))
    return Family(kernels, [filter_spec("srukf", "srukf", kernels, model.measurements, defaults={"kappa": 0.0},
                                        covariance="cholesky")])


register_family("srukf", srukf_kernels, long_compile=True)      # f_d at the sigma points

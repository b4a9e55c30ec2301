"""Manifold UKF for any model with unit-quaternion states: family ``"mukf"`` (additive noise).

On the chart of ``chart.py`` and the shared pieces of ``manifold.py``.

**UKF.** 2 n_e + 1 sigma points δ_i = 0, ±columns of chol((n_e + κ) P) (Julier's weights, as the
Kalman UKF), mapped through the retraction χ_i = x̂ ⊞ δ_i. Prediction: χ_i through f_d, the mean
of each quaternion by the eigenvector method (Markley et al., "Averaging quaternions", JGCD 30(4)
2007; no LAPACK, ``chart.quaternion_mean``), ordinary states by the weighted mean,
residuals χ_i⁺ ⊟ x̄ in error coordinates. Update: sigma points redrawn from (x̂, P), the
measurement's sigma values as the Kalman UKF (angle outputs wrapped), residuals of the state
are the offsets δ_i exactly, correction by the retraction.

Masks, gates, status codes and input checks: ``manifold.py``. The noise-sampling UKFs of paper 000
are ``quaternion_filters.py``.
"""
from __future__ import annotations

import casadi as ca

from symkf.models.base import Model
from .. import linalg
from ..model_functions import ModelFunctions, Symbols
from ..spec import Family
from .chart import ManifoldOptions
from .framework import compose_step, filter_spec, make_kernel, masked_noise, register_family
from .kalman import UPDATE_INPUTS, _angle_difference, _predict_doc, sigma_points
from .manifold import (ManifoldFunctions, ManifoldSymbols, chart_innovation, error_process_noise, measurement_input,
                       predict_kernel, require_quaternion, update_outputs)

#: Default UKF scaling: κ = 0 as the Kalman UKF (weights 0 and 1/(2 n_e)).
DEFAULT_KAPPA = 0.0


def mukf_predict_expr(model: Model, mf: ManifoldFunctions, ms: ManifoldSymbols):
    s, P = ms.base.sym, ms.sym["P"]
    offsets, weights, ok = sigma_points(ca.SX.zeros(P.shape[0]), P, s["kappa"])
    propagated = [mf.step(s["t"], s["dt"], mf.retract(s["x"], d), s["u"], s["p"]) for d in offsets]
    x_mean = mf.mean(propagated, weights)
    residuals = [mf.local(pt, x_mean) for pt in propagated]
    P_pred = sum((w * r @ r.T for w, r in zip(weights, residuals)), ca.SX.zeros(P.shape)) + \
        error_process_noise(model, mf, ms.base, ms.sym["Q"], s["x"], s["t"], s["dt"])
    return x_mean, linalg.symmetrize(P_pred), ok, mf.chart.in_domain_all(offsets)


def mukf_update_expr(mf: ManifoldFunctions, ms: ManifoldSymbols, name: str, msym: dict, wrap):
    s, P = ms.base.sym, ms.sym["P"]
    t, x = s["t"], s["x"]
    m = measurement_input(mf.model, ms, name, msym)
    offsets, weights, ok = sigma_points(ca.SX.zeros(P.shape[0]), P, s["kappa"])
    predicted = [mf.h[name](t, mf.retract(x, d), s["u"], s["p"], msym["q"]) for d in offsets]
    z_pred = mf.measurement_mean(name, predicted, weights)
    if mf.model.measurements[name].quaternion:
        dz = [m.mask * mf.residual(name, zi, z_pred) for zi in predicted]
    else:
        dz = [m.mask * _angle_difference(zi, z_pred, wrap) for zi in predicted]
    R = masked_noise(mf.measurement_noise(name, msym["R"], t, x, s["u"], s["p"], msym["q"]), m.mask)
    S = linalg.symmetrize(sum((w * d @ d.T for w, d in zip(weights, dz)), ca.SX.zeros(R.shape)) + R)
    Pxz = sum((w * a @ b.T for w, a, b in zip(weights, offsets, dz)), ca.SX.zeros(P.shape[0], R.shape[0]))
    L, ok_s = linalg.cholesky(S)
    U = linalg.solve_lower(L, Pxz.T)                 # K y = Uᵀ L⁻¹ y, K S Kᵀ = Uᵀ U
    y = chart_innovation(mf, name, m, z_pred, wrap)
    correction = U.T @ linalg.solve_lower(L, y)
    x_new = mf.retract(x, correction)
    P_new = linalg.symmetrize(P - U.T @ U)
    nis = ca.sumsqr(linalg.solve_lower(L, y))
    in_domain = mf.chart.in_domain(correction) * mf.chart.in_domain_all(offsets)
    return (x_new, P_new, y, S, ok * ok_s, nis, m.finite, in_domain), m


def mukf_kernels(model: Model, symbols: Symbols, fns: ModelFunctions) -> Family:
    require_quaternion(model, "mukf")
    mf, ms = ManifoldFunctions(model, fns), ManifoldSymbols(model, symbols)
    s = symbols.sym
    x_pred, P_pred, ok, in_domain = mukf_predict_expr(model, mf, ms)
    ok = ok * (s["kappa"] + model.n_error > 0)
    doc = _predict_doc(model, "Manifold UKF", f"{2 * model.n_error + 1} sigma points x (+) d_i, quaternion "
                       "eigenvector mean, residuals in error coordinates")
    predict = predict_kernel("mukf_predict", doc, ms, mf, x_pred, P_pred, ok,
                             ["t", "dt", "x", "P", "u", "p", "Q", "kappa"], in_domain=in_domain)
    kernels = [predict]
    for name, meas in model.measurements.items():
        msym, marg = ms.measurement(name)
        upd, m = mukf_update_expr(mf, ms, name, msym, meas.wrap)
        kernels.append(make_kernel(
            f"mukf_update_{name}", f"Manifold UKF update with '{name}': sigma points x (+) d_i redrawn, correction "
            "by the retraction (masked, gated).", symbols, msym, marg, UPDATE_INPUTS + ["kappa"],
            update_outputs(mf.chart, upd, s["x"], ms.sym["P"], msym, m)))
        kernels.append(compose_step(f"mukf_step_{name}", predict, kernels[-1]))
    return Family(kernels, [filter_spec("mukf", "manifold_ukf", kernels, model.measurements,
                                        defaults={"kappa": DEFAULT_KAPPA})])


register_family("mukf", mukf_kernels, quaternions=True, options=(ManifoldOptions,))

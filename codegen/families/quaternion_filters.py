"""Noise-sampling manifold UKFs (paper 000's filters) on the manifold filters' primitives.

Families ``"sukf"`` and ``"aukf"`` (filters of the same names), for any model with
``quaternion_state`` whose measurements declare their own noise (``Model.measurement_noise``).
They share everything with the other manifold filters: the chart of ``chart.py`` (retraction
x ⊞ δ, local coordinates x ⊟ x̂, both per the model's ``manifold_*`` options, and the quaternion
mean (36)-(38)), and from ``manifold.py`` the step f_d(t, dt, x, u, p, w) with the process noises w
as arguments, the measurement h(t, x, u, p, q, v) with its noise v, masks, gates, status codes and
the update's outputs. What differs from the generic manifold UKF (``mukf``, additive noise) is
where the noise enters: it is sampled.

Leeghim, Choi, Bang, Park, "Spacecraft Attitude Estimation by Unscented Filtering" (2008):

- ``sukf`` ("separated" spaces, the paper's efficient UKF). Propagation in [δx, w] (eqs (9)-(15),
  (39)-(45)): 2(n_e + n_w) + 1 sigma points from blockdiag(√P, √(Q/Δt)) (one small Cholesky factor
  per block, eq (9)), γ = √(n + κ), weights κ/(n + κ) and 1/(2(n + κ)) (eq (12) prints κ in the
  numerator of the outer weights, a typo: the weights must sum to 1); each point χ_i = x̂ ⊞ δ_i
  goes through f_d with its own noise sample w_i; mean by the quaternion mean (36)-(38); P⁻ from
  the residuals χ_i⁺ ⊟ x̄ (no additive Q: the noise is in the points). Update in [δx, v]
  (eqs (16)-(22), (46)-(53)): 2(n_e + n_v) + 1 points from blockdiag(√P, √R), z_i = h(χ_i, v_i),
  the mean predicted measurement (the quaternion mean (38) for a quaternion measurement),
  P^yy = Σ W dz dzᵀ and P^xy = Σ W δ_i dzᵀ with dz_i = z_i ⊟ z̄, gain (5), innovation z ⊟ z̄ (50),
  correction by the retraction (51)-(52), P⁺ = P⁻ - K P^yy Kᵀ (7).
  For paper 000 (n_e = 6, n_w = 6, n_v = 3): 25 and 19 points.
- ``aukf``: the same UKF in the full augmented space [δx, w, v] (one full Cholesky factor of
  blockdiag(P, Q/Δt, R) per step, 2(n_e + n_w + n_v) + 1 = 31 points for paper 000); the update
  reuses the propagated sigma set. For the paper's cost comparison; a model with one measurement.

κ is not given by the paper: the default κ = 1 keeps every weight positive (κ = 3 - n would make
W_0 < 0).
"""
from __future__ import annotations

import casadi as ca

from symkf.models.base import Model
from .. import linalg
from ..discretize import CALLED_OPTIONS
from ..model_functions import ModelFunctions, Symbols
from ..spec import Arg, Family, Kernel
from .chart import ManifoldOptions, quaternion_mean
from .framework import compose_step, filter_spec, make_kernel, register_family
from .kalman import UPDATE_INPUTS
from .manifold import (ManifoldFunctions, ManifoldSymbols, measurement_input, predict_kernel, predict_status,
                       require_quaternion, update_outputs)

#: UKF scaling κ used unless given: keeps every weight positive (paper 000 leaves κ open).
DEFAULT_KAPPA = 1.0


# ---------------------------------------------------------------------- quaternion mean
def mean_kernel(symbols: Symbols, n_points: int) -> Kernel:
    """``quaternion_mean_<n>``: the eigenvector mean alone (for tests and users)."""
    quaternions, weights, q_ref = ca.SX.sym("quaternions", 4, n_points), ca.SX.sym("weights", n_points), \
        ca.SX.sym("q_ref", 4)
    mean = ca.Function(f"{symbols.model.name}_quaternion_mean_{n_points}", [quaternions, weights, q_ref],
                       [quaternion_mean(quaternions, weights, q_ref)], CALLED_OPTIONS)
    extra_sym = {"quaternions": quaternions, "weights": weights, "q_ref": q_ref}
    extra_arg = {"quaternions": Arg("quaternions", (4, n_points), "-", "unit quaternions, one per column"),
                 "weights": Arg("weights", (n_points, 1), "-", "weights W_i (sum 1; may include a negative W_0)"),
                 "q_ref": Arg("q_ref", (4, 1), "-", "reference quaternion fixing the sign of the mean"),
                 "q": Arg("q", (4, 1), "-", "the mean quaternion (eq 38)")}
    return make_kernel(f"quaternion_mean_{n_points}", "Quaternion mean (36)-(38): eigenvector of N for its smallest "
                       "eigenvalue, by shifted repeated squaring (no LAPACK).", symbols, extra_sym, extra_arg,
                       ["quaternions", "weights", "q_ref"],
                       [("q", mean(quaternions, weights, q_ref)), ("status", ca.SX(0))])


# ---------------------------------------------------------------------- sigma sets with noise
def sigma_set(blocks: list[ca.SX], kappa: ca.SX, full: bool = False):
    """Offsets [0, +γ L_i..., -γ L_i...] of blockdiag(blocks) (eqs (9), (12)-(13), (18)-(19)), the
    weights κ/(n + κ), 1/(2(n + κ)) and 0/1 flags (factorised; n + κ > 0). ``full``: one Cholesky
    factor of the whole block-diagonal matrix (the augmented UKF) instead of one per block."""
    if full:
        L, ok = linalg.cholesky(ca.diagcat(*blocks))
    else:
        factors, flags = zip(*[linalg.cholesky(b) for b in blocks])
        L, ok = ca.diagcat(*factors), _all(flags)
    n = L.shape[0]
    positive = n + kappa > 0                           # else refused: SYMKF_ERR_DOMAIN
    gamma = ca.sqrt(ca.fmax(n + kappa, 0))
    columns = [gamma * L[:, i] for i in range(n)]
    offsets = [ca.SX.zeros(n, 1)] + columns + [-c for c in columns]
    scale = linalg.guarded(n + kappa, positive)
    return offsets, [kappa / scale] + [0.5 / scale] * (2 * n), ok, positive


def _all(flags) -> ca.SX:
    result = ca.SX(1)
    for flag in flags:
        result = result * flag
    return result


def _weighted_outer(weights, left, right) -> ca.SX:
    return sum((w * a @ b.T for w, a, b in zip(weights, left, right)), ca.SX.zeros(left[0].shape[0], right[0].shape[0]))


def propagate_sigma_set(mf, ms, offsets, weights):
    """Eqs (41)-(45) per point: χ_i = x̂ ⊞ δ_i through f_d with its own noise sample w_i; the mean
    (15) with the quaternion mean (38), the residuals χ_i⁺ ⊟ x̄ and P⁻ = Σ W r rᵀ."""
    s, ne, nw = ms.base.sym, mf.model.n_error, len(mf.model.noises)
    points = [mf.chart.project(mf.fd_noisy(s["t"], s["dt"], mf.retract(s["x"], o[:ne]), s["u"], s["p"],
                                           o[ne:ne + nw])) for o in offsets]
    mean = mf.mean(points, weights)
    residuals = [mf.local(pt, mean) for pt in points]
    return points, mean, residuals, linalg.symmetrize(_weighted_outer(weights, residuals, residuals))


def sigma_update(mf, ms, name: str, msym: dict, m, x_hat, P, deviations, points, noise, weights):
    """Eqs (20)-(22), (50)-(52): z_i = h(χ_i, v_i), mean z̄, P^yy, P^xy, gain, innovation z ⊟ z̄,
    correction x̂ ⊞ K y and P⁺ = P - K P^yy Kᵀ. Returns the update tuple of
    ``manifold.update_outputs`` without its finite and domain flags."""
    s = ms.base.sym
    z_points = [mf.h_noisy[name](s["t"], pt, s["u"], s["p"], msym["q"], v) for pt, v in zip(points, noise)]
    z_mean = mf.measurement_mean(name, z_points, weights)
    dz = [m.mask * mf.residual(name, z, z_mean) for z in z_points]
    P_yy = linalg.symmetrize(_weighted_outer(weights, dz, dz) + ca.diag(1 - m.mask))   # masked: identity
    P_xy = _weighted_outer(weights, deviations, dz)
    L, ok = linalg.cholesky(P_yy)
    K = linalg.cholesky_solve(L, P_xy.T).T
    y = m.mask * mf.residual(name, m.z, z_mean)
    correction = K @ y
    P_new = linalg.symmetrize(P - K @ P_yy @ K.T)
    return mf.retract(x_hat, correction), P_new, y, P_yy, ok, ca.sumsqr(linalg.solve_lower(L, y)), correction


# ---------------------------------------------------------------------- separated-space UKF
def sukf_predict_kernel(mf, ms) -> Kernel:
    s = ms.base.sym
    Q_held = ms.sym["Q"] / linalg.guarded(s["dt"], s["dt"] > 0)
    offsets, weights, ok, positive = sigma_set([ms.sym["P"], Q_held], s["kappa"])
    _, mean, _, P_pred = propagate_sigma_set(mf, ms, offsets, weights)
    n = len(offsets)
    return predict_kernel("sukf_predict", f"Separated-space UKF propagation in [x, w] ({n} sigma points x (+) d_i "
                          "through f_d with noise samples w_i, eqs (9)-(15), (39)-(45); quaternion mean (38)).",
                          ms, mf, mean, P_pred, ok, ["t", "dt", "x", "P", "u", "p", "Q", "kappa"],
                          in_domain=positive * _state_offsets_in_domain(mf, offsets))


def _state_offsets_in_domain(mf, offsets) -> ca.SX:
    return mf.chart.in_domain_all([o[:mf.model.n_error] for o in offsets])


def sukf_update_kernel(mf, ms, name: str) -> Kernel:
    s, ne = ms.base.sym, mf.model.n_error
    msym, marg = ms.measurement(name)
    m = measurement_input(mf.model, ms, name, msym)
    offsets, weights, ok, positive = sigma_set([ms.sym["P"], msym["R"]], s["kappa"])
    points = [mf.retract(s["x"], o[:ne]) for o in offsets]
    deviations = [o[:ne] for o in offsets]            # χ_i ⊟ x̂ = δ_i exactly (eqs (41)-(42))
    x_new, P_new, y, P_yy, ok_s, nis, correction = sigma_update(
        mf, ms, name, msym, m, s["x"], ms.sym["P"], deviations, points, [o[ne:] for o in offsets], weights)
    in_domain = positive * _state_offsets_in_domain(mf, offsets) * mf.chart.in_domain(correction)
    upd = (x_new, P_new, y, P_yy, ok * ok_s, nis, m.finite, in_domain)
    return make_kernel(f"sukf_update_{name}", f"Separated-space UKF update with '{name}' in [x, v] ({len(offsets)} "
                       "sigma points, eqs (16)-(22), (46)-(53); masked, gated).", ms.base, msym, marg,
                       UPDATE_INPUTS + ["kappa"], update_outputs(mf.chart, upd, s["x"], ms.sym["P"], msym, m))


def sukf_kernels(model: Model, symbols: Symbols, fns: ModelFunctions) -> Family:
    mf, ms = _setup(model, symbols, fns, "sukf")
    predict = sukf_predict_kernel(mf, ms)
    kernels = [mean_kernel(symbols, 2 * (model.n_error + len(model.noises)) + 1), predict]
    for name in model.measurements:
        kernels.append(sukf_update_kernel(mf, ms, name))
        kernels.append(compose_step(f"sukf_step_{name}", predict, kernels[-1]))
    return Family(kernels, [filter_spec("sukf", "separated_ukf", kernels, model.measurements,
                                        defaults={"kappa": DEFAULT_KAPPA})])


# ---------------------------------------------------------------------- full augmented UKF
def _augmented_set(mf, ms, R):
    """The [δx, w, v] sigma set (one full Cholesky factor), propagated."""
    s = ms.base.sym
    Q_held = ms.sym["Q"] / linalg.guarded(s["dt"], s["dt"] > 0)
    offsets, weights, ok, positive = sigma_set([ms.sym["P"], Q_held, R], s["kappa"], full=True)
    points, mean, residuals, P_pred = propagate_sigma_set(mf, ms, offsets, weights)
    return offsets, weights, points, mean, residuals, P_pred, ok, positive * _state_offsets_in_domain(mf, offsets)


def aukf_kernels(model: Model, symbols: Symbols, fns: ModelFunctions) -> Family:
    mf, ms = _setup(model, symbols, fns, "aukf")
    if len(model.measurements) != 1:
        raise ValueError(f"filter family 'aukf' augments the state with one measurement's noise; model "
                         f"'{model.name}' has {len(model.measurements)}")
    (name,) = model.measurements
    s, ne, nw = symbols.sym, model.n_error, len(model.noises)
    msym, marg = ms.measurement(name)
    offsets, weights, points, x_pred, residuals, P_pred, ok, in_domain = _augmented_set(mf, ms, msym["R"])
    n = len(offsets)
    inputs = ["t", "dt", "x", "P", "u", "p", "Q", "R", "kappa"]
    predict = predict_kernel("aukf_predict", f"Augmented UKF propagation in [x, w, v] ({n} sigma points; the v "
                             "columns are carried unused).", ms, mf, x_pred, P_pred, ok, inputs,
                             {"R": msym["R"]}, {"R": marg["R"]}, in_domain)
    m = measurement_input(model, ms, name, msym)
    x_new, P_new, y, P_yy, ok_s, nis, correction = sigma_update(
        mf, ms, name, msym, m, x_pred, P_pred, residuals, points, [o[ne + nw:] for o in offsets], weights)
    upd = (x_new, P_new, y, P_yy, ok_s, nis, m.finite, mf.chart.in_domain(correction))
    outputs = update_outputs(mf.chart, upd, x_pred, P_pred, msym, m)
    pre = predict_status(mf, symbols, ok, in_domain)
    failed_early = pre != 0             # as compose_step: a failed propagation returns the inputs
    outputs = [(k, linalg.select(failed_early, {"x": s["x"], "P": ms.sym["P"], "status": pre}.get(k, v), v))
               for k, v in outputs]
    step = make_kernel(f"aukf_step_{name}", f"Augmented UKF step in [x, w, v] ({n} sigma points): propagation and, "
                       "if mask = 1, the update from the same sigma set (masked, gated).", symbols, msym, marg,
                       ["t", "dt", "x", "P", "u", "p", "Q", "q", "z", "mask", "R", "gate", "kappa"], outputs,
                       carried=("x", "P"), per_step=("t", "dt", "u", "q", "z", "mask"))
    return Family([predict, step], [filter_spec("aukf", "augmented_ukf", [predict, step], model.measurements,
                                                defaults={"kappa": DEFAULT_KAPPA})])


def _setup(model: Model, symbols: Symbols, fns: ModelFunctions, family: str):
    require_quaternion(model, family)
    if not model.noises:
        raise ValueError(f"filter family '{family}' samples the process noises: model '{model.name}' declares none "
                         "(Model.noise())")
    mf = ManifoldFunctions(model, fns)
    if mf.fd_noisy is None:
        raise ValueError(f"filter family '{family}' needs the step with its noises: set manifold_noise 'held' or "
                         f"declare an exact step (model '{model.name}')")
    missing = [name for name in model.measurements if name not in mf.h_noisy]
    if missing:
        raise ValueError(f"filter family '{family}' samples the measurement noise: measurements {missing} of model "
                         f"'{model.name}' declare none (Model.measurement_noise())")
    return mf, ManifoldSymbols(model, symbols)


register_family("sukf", sukf_kernels, quaternions=True, options=(ManifoldOptions,))
register_family("aukf", aukf_kernels, quaternions=True, options=(ManifoldOptions,))

"""Fused EKF and UKF steps as CasADi Functions (kernels), derived from a Model.

EKF: x- = f_d(x), P- = F P F^T + Q_d; update with the Joseph form
P+ = (I - K H) P- (I - K H)^T + K R K^T.

Process noise Q_d over one step [t, t + dt]:
- a model without ``noise()``: additive, Q is the n x n power spectral density of the state
  noise and Q_d = Q dt;
- a model with noises w (``noise()``, entering f non-additively): Q is the nw x nw power
  spectral density of w and Q_d = G Q G^T dt with G = df/dw evaluated at the start of the step
  (t, x, u, p, w = 0); the mean is propagated with w = 0. This is the first-order (rectangle)
  discretisation of the continuous noise input; Van Loan's exact form differs by O(dt^2).

UKF (paper 004, eqs (1)-(3), Julier & Uhlmann): 2n+1 sigma points x, x +/- columns of
chol((n + kappa) P), weights W_0 = kappa/(n + kappa), W_i = 1/(2(n + kappa)); the update redraws
sigma points from the predicted mean and covariance. Angle components of a measurement are
averaged and differenced on the circle (wrapped to (-pi, pi]).

Every update takes an availability ``mask`` (1 = use, 0 = ignore): a masked component's
innovation is zero, its row of H and its sigma-point deviations are zero and its noise variance
is replaced by 1, so it contributes exactly nothing; an all-masked update returns x and P unchanged.
A failed Cholesky factorisation returns status SYMKF_ERR_NOT_PD and the inputs x, P unchanged.

**Input checks.** The kernels do not test their inputs for NaN/Inf, except an update's x and P: every
caller does first, with one rule (every input finite; z only where its mask is > 0.5): the C
wrappers and run loops (codegen/c_backend/api.py) and the CasADi-VM backend (runtime/backends.py),
as for the manifold family. An in-kernel test repeated theirs at one multiply-add per input entry
(about 90 in the launcher's predict, 70 in its update) on every step. The update's x
and P are tested: in a fused step they are the prediction's outputs, which no caller has seen.

A predict kernel's x and P are its result only with status 0: nothing reads them otherwise (the C
API and the VM backend return a nonzero status without copying the outputs, and the fused step
keeps its inputs when the prediction failed), so they are not selected back to the inputs: 42
selections fewer per step. An update's x and P are selected (a gated update returns its
inputs with status SYMKF_GATED, and they are written).
"""
from __future__ import annotations

from dataclasses import dataclass, fields
from typing import ClassVar

import casadi as ca

from symkf.models.base import Model
from .. import linalg
from ..discretize import measurement_function
from ..model_functions import ModelFunctions, Symbols
from ..spec import STATUS_DOMAIN, STATUS_NOT_PD, Arg, Family, option
from .framework import (all_finite, compose_step, filter_spec, innovation, make_kernel, masked_noise, register_family,
                        update_outputs)
from .iterated import IteratedOptions, iterated_update_expr, iterations
from .rts import cross_covariance, smooth_kernel


def lockstep_vector_math_option(family: str, launcher_instructions: str):
    """``<family>_lockstep_vector_math``: libmvec in the lockstep lanes' prediction (EKF and UKF alike)."""
    return option(False, f"with {family}_lockstep, the prediction's lanes (and the smoother's backward step's) "
                         "call glibc's libmvec for sin, cos, exp, log, pow and atan2: launcher "
                         f"{launcher_instructions} instructions per run-step; each run's numbers differ from the "
                         "scalar code's by its round-off (a few ulp a call); off by default, and libm's on a host "
                         "without glibc's libmvec")


@dataclass(frozen=True)
class UkfOptions:
    """The UKF's options of its generated C (the same numbers either way)."""

    centre_free: bool = option(True, "with kappa = 0 (centre weight exactly 0) skip propagating the centre sigma "
                                     "point, picked at call time; the same numbers as propagating it")

    lanes: bool = option(False, "the host library propagates the sigma points 4 at a time in SIMD lanes on an AVX2 "
                                "CPU (libmvec's sin/cos; codegen/c_backend/lanes.py): about half the UKF's "
                                "instructions, but round-off differs from the flight bundle's scalar code, which "
                                "moves chaotic excursion runs (off by default: the library computes what the "
                                "bundle computes)")

    lockstep: bool = option(False, "the host library steps 4 Monte Carlo runs at once in AVX2 vectors "
                                   "(Filter.run_lockstep; codegen/c_backend/lockstep.py): the scalar code's numbers "
                                   "bit for bit; off by default: its C adds compile time to every build and edit")

    lockstep_vector_math: bool = lockstep_vector_math_option("ukf", "15.5k instead of 32.2k")

    lanes_update: bool = option(False, "with ukf_lanes, the update's h at the sigma points in lanes too (libmvec's "
                                       "atan2, sin, cos: 18.4k instead of 23.5k instructions per launcher step; its "
                                       "round-off moves some campaign runs by up to 1e-4 relative: off by default)")

    prefix: ClassVar[str] = "ukf_"

    @classmethod
    def of(cls, config) -> "UkfOptions":
        return cls(*(bool(config.get(f"{cls.prefix}{f.name}", f.default)) for f in fields(cls)))


@dataclass(frozen=True)
class LockstepOptions:
    """The host library's lockstep loop of the EKF's steps (the flight bundle has none)."""

    lockstep: bool = option(False, "the host library steps 4 Monte Carlo runs at once in AVX2 vectors "
                                   "(Filter.run_lockstep; codegen/c_backend/lockstep.py): the scalar code's numbers "
                                   "bit for bit; off by default: its C adds compile time to every build and edit")

    lockstep_vector_math: bool = lockstep_vector_math_option("ekf", "4.8k instead of 6.6k")

    prefix: ClassVar[str] = "ekf_"


# ---------------------------------------------------------------------- process noise
def noise_symbols(model: Model) -> tuple[dict, dict]:
    """The Q argument of the predict kernels: {} (the n x n additive Q of Symbols) for a model
    without noises, else an nw x nw Q, the power spectral density of the noises w."""
    if not model.noises:
        return {}, {}
    nw = len(model.noises)
    names = [v.name for v in model.noises]
    units = ", ".join(f"({v.unit})^2 s" for v in model.noises)
    return {"Q": ca.SX.sym("Q", nw, nw)}, {"Q": Arg("Q", (nw, nw), units, f"power spectral density of the "
                                                     f"process noises w {names} (discrete: G Q G^T dt, G = df/dw)")}


def process_noise(symbols: Symbols, fns: ModelFunctions, Q, x, t, dt):
    """Q_d over [t, t + dt]: Q dt (additive), or G Q G^T dt with G = df/dw at (t, x) (noise())."""
    if fns.noise_gain is None:
        return Q * dt
    G = fns.noise_gain(t, x, symbols.sym["u"], symbols.sym["p"])
    return G @ Q @ G.T * dt


def _predict_doc(model: Model, name: str, detail: str) -> str:
    noise = "G Q G^T dt, G = df/dw at the step start" if model.noises else "Q dt"
    return f"{name} prediction from t to t + dt ({detail}; process noise {noise})."


# ---------------------------------------------------------------------- EKF
def ekf_prediction(symbols: Symbols, fns: ModelFunctions, x, P, t, dt, Q):
    """x- = f_d(x), P- = F P F^T + Q_d, and F (the smoother's cross-covariance is P F^T)."""
    s = symbols.sym
    x_next, F = fns.for_filter("ekf").fd_and_jac(t, dt, x, s["u"], s["p"])
    FPF, Qd = linalg.sandwich(F, P), process_noise(symbols, fns, Q, x, t, dt)
    return x_next, linalg.symmetric(P.shape[0], lambda i, j: FPF[i, j] + linalg.symmetric_part(Qd, i, j)), F


def ekf_predict_expr(symbols: Symbols, fns: ModelFunctions, x, P, t, dt, Q):
    return ekf_prediction(symbols, fns, x, P, t, dt, Q)[:2]


def ekf_update_expr(symbols: Symbols, fns: ModelFunctions, name: str, msym: dict, wrap, x, P, t):
    s = symbols.sym
    n = symbols.model.nx
    z_pred, H_full = fns.h_and_jac[name](t, x, s["u"], s["p"], msym["q"])
    mask = msym["mask"]
    H = ca.diag(mask) @ H_full
    R = masked_noise(msym["R"], mask)
    y = innovation(msym["z"], z_pred, mask, wrap)
    S = linalg.symmetrize(H @ P @ H.T + R)
    L, ok = linalg.cholesky(S)
    K = linalg.cholesky_solve(L, H @ P).T           # K = P H^T S^-1
    I_KH = ca.SX.eye(n) - K @ H
    x_new = x + K @ y
    P_new = linalg.sandwich(I_KH, P) + linalg.sandwich(K, R)          # Joseph form, lower half mirrored
    nis = ca.sumsqr(linalg.solve_lower(L, y))                 # y^T S^-1 y, for the gate
    return x_new, P_new, y, S, ok * linalg.psd_flag(P), nis


def update_inputs_finite(symbols: Symbols) -> ca.SX:
    """The update's x and P are finite: the one check of its inputs the kernel makes itself (see
    "Input checks" in the module docstring: a fused step's predicted x and P reach the update
    without passing a caller's test; an overflowed prediction is reported as NONFINITE)."""
    s = symbols.sym
    return all_finite([s["x"], s["P"]])


UPDATE_INPUTS = ["t", "x", "P", "u", "p", "q", "z", "mask", "R", "gate"]


def predict_status(ok: ca.SX) -> ca.SX:
    """NOT_PD unless ``ok`` (P could be factorised), else 0 (the inputs are finite: "Input checks")."""
    return linalg.select(ok, 0, STATUS_NOT_PD)


def ekf_kernels(model: Model, symbols: Symbols, fns: ModelFunctions) -> Family:
    s = symbols.sym
    qsym, qarg = noise_symbols(model)
    Q = qsym.get("Q", s["Q"])
    x_pred, P_pred = ekf_predict_expr(symbols, fns, s["x"], s["P"], s["t"], s["dt"], Q)
    status = predict_status(linalg.psd_flag(s["P"]))
    kernels = [make_kernel("ekf_predict", _predict_doc(model, "EKF", "P = F P F^T + Q_d"),
                       symbols, qsym, qarg, ["t", "dt", "x", "P", "u", "p", "Q"],
                       [("x", x_pred), ("P", P_pred), ("status", status)])]
    for name, meas in model.measurements.items():
        msym, marg = symbols.measurement(name)
        iterated = iterations(fns.config) > 1               # Gauss-Newton updates (iterated.py)
        upd = (iterated_update_expr if iterated else ekf_update_expr)(symbols, fns, name, msym, meas.wrap, s["x"],
                                                                       s["P"], s["t"])
        kind = f"iterated, {iterations(fns.config)} linearisations; " if iterated else ""
        kernels.append(make_kernel(
            f"ekf_update_{name}", f"EKF update with measurement '{name}' at time t ({kind}Joseph form, masked, gated).",
            symbols, msym, marg, UPDATE_INPUTS,
            update_outputs(upd, s["x"], s["P"], msym["gate"], msym["mask"], update_inputs_finite(symbols))))
        kernels.append(compose_step(f"ekf_step_{name}", kernels[0], kernels[-1]))
    x_pred, P_pred, F = ekf_prediction(symbols, fns, s["x"], s["P"], s["t"], s["dt"], Q)
    kernels.append(smooth_kernel("ekf_smooth", "EKF RTS smoother: one backward step from step k + 1 to k "
                                 "(G = P F^T (P-)^-1).", symbols, qsym, qarg, ["t", "dt", "x", "P", "u", "p", "Q"],
                                 (x_pred, P_pred, s["P"] @ F.T, linalg.psd_flag(s["P"]))))
    return Family(kernels, [filter_spec("ekf", "ekf", kernels, model.measurements, smooth="ekf_smooth")])


# ---------------------------------------------------------------------- UKF
def sigma_factor(P: ca.SX, kappa: ca.SX):
    """L = chol((n + kappa) P) (lower triangular), the 2n + 1 weights, and a 0/1 success flag."""
    n = P.shape[0]
    scale = n + kappa
    L, ok = linalg.cholesky(scale * P)
    safe_scale = linalg.guarded(scale, scale > 0)     # n + kappa <= 0 is refused (SYMKF_ERR_DOMAIN)
    weights = [kappa / safe_scale] + [0.5 / safe_scale] * (2 * n)
    return L, weights, ok * (scale > 0)


def sigma_columns(x: ca.SX, L: ca.SX) -> list[ca.SX]:
    """Eq (1): x, x + L_i, x - L_i for the columns L_i of L."""
    n = x.shape[0]
    return [x] + [x + L[:, i] for i in range(n)] + [x - L[:, i] for i in range(n)]


def sigma_offsets(P: ca.SX, kappa: ca.SX):
    """Eq (1)-(2) of paper 004 as offsets from the mean: 0, +/- columns of chol((n + kappa) P);
    the weights, and a 0/1 success flag."""
    L, weights, ok = sigma_factor(P, kappa)
    n = P.shape[0]
    return [None] + [L[:, i] for i in range(n)] + [-L[:, i] for i in range(n)], weights, ok


def sigma_points(x: ca.SX, P: ca.SX, kappa: ca.SX):
    """Eq (1)-(2) of paper 004: points (columns), weights, and a 0/1 success flag."""
    L, weights, ok = sigma_factor(P, kappa)
    return sigma_columns(x, L), weights, ok


def _weighted_mean(points: list[ca.SX], weights: list, wrap: tuple[bool, ...] | None = None) -> ca.SX:
    """Weighted mean; wrapped components are averaged as deviations from the first point."""
    if not wrap or not any(wrap):
        return sum((w * pt for w, pt in zip(weights, points)), ca.SX.zeros(points[0].shape))
    ref = points[0]
    deviation = sum((w * _angle_difference(pt, ref, wrap) for w, pt in zip(weights, points)),
                    ca.SX.zeros(ref.shape))
    return ref + deviation


def _angle_difference(a: ca.SX, b: ca.SX, wrap: tuple[bool, ...]) -> ca.SX:
    return ca.vertcat(*[linalg.wrap_angle(a[i] - b[i]) if wrap[i] else a[i] - b[i] for i in range(a.shape[0])])


def ukf_predict_expr(symbols: Symbols, fns: ModelFunctions, x, P, t, dt, Q):
    return ukf_propagation(symbols, fns, x, P, t, dt, Q)[:3]


def ukf_propagation(symbols: Symbols, fns: ModelFunctions, x, P, t, dt, Q):
    """The UKF prediction (x-, P-, success flag) and what the unscented smoother needs besides:
    the weights, each sigma point's offset from x and each propagated point's from x-."""
    if fns.config.precision == "float":
        return ukf_predict_deviations(symbols, fns, x, P, t, dt, Q)
    s = symbols.sym
    n = x.shape[0]
    L, weights, ok = sigma_factor(P, s["kappa"])
    # one call, split only at an event; L lower triangular: a point x + L_i leaves x_0..x_i-1 as
    # they are, and the function sees it (terms of those components are shared with x's); with
    # W_0 = 0 (kappa = 0) the centre point is not propagated (its weight makes it add exact zeros)
    inputs, propagation = {"x": ca.SX.sym("x", n), "L": ca.SX.sym("L", ca.Sparsity.lower(n))}, fns.for_filter("ukf")
    if UkfOptions.of(fns.config).centre_free:
        moved = propagation.fd_at_points_weighted("sigma", inputs, sigma_columns)(weights[0], t, dt, x, ca.tril(L),
                                                                                  s["u"], s["p"])
    else:
        moved = propagation.fd_at_points("sigma", inputs, sigma_columns)(t, dt, x, ca.tril(L), s["u"], s["p"])
    propagated = [moved[:, i] for i in range(2 * n + 1)]
    x_pred = _weighted_mean(propagated, weights)
    moved = [pt - x_pred for pt in propagated]
    offsets = [ca.SX.zeros(n)] + [L[:, i] for i in range(n)] + [-L[:, i] for i in range(n)]
    return (x_pred, _sigma_covariance(weights, moved, process_noise(symbols, fns, Q, x, t, dt)), ok,
            weights, offsets, moved)


def _sigma_covariance(weights: list, deviations: list[ca.SX], Qd: ca.SX) -> ca.SX:
    """Eq (3): sum_i W_i d_i d_i^T + Q_d, every term in order and then symmetrized. Grouping the
    equal weights or computing one triangle saves ~1k instructions per UKF step but moves P by
    round-off, which the campaign's excursion runs amplify into Table 3 (20 Hz large V 0.255 ->
    0.169 m/s; a paper-like 10 Hz run turned diverged): kept as it was, bit for bit."""
    return linalg.symmetrize(_weighted_products(weights, deviations, deviations) + Qd)


def _weighted_products(weights: list, A: list[ca.SX], B: list[ca.SX]) -> ca.SX:
    """sum_k (w_k a_k) b_k^T, term by term in order (the bit pattern of every earlier release)."""
    return sum((w * a @ b.T for w, a, b in zip(weights, A, B)), ca.SX.zeros(A[0].shape[0], B[0].shape[0]))


def ukf_predict_deviations(symbols: Symbols, fns: ModelFunctions, x, P, t, dt, Q):
    """The UKF prediction of a float build, in deviation form: each sigma point's offset d_i is
    propagated as an increment of x (x + d_i -> x + y_i, codegen/discretize.py), the mean is
    x + sum w_i y_i and the covariance sum w_i (y_i - ybar)(y_i - ybar)^T + Q_d. The same numbers as
    :func:`ukf_predict_expr` in exact arithmetic; in float, the deviations are never formed as
    differences of numbers of the state's magnitude (a geocentric radius near 6.6e6 m, or an
    altitude of 3e5 m, has a float spacing of 0.5 m or 0.03 m against a 1-sigma of ~0.5 m)."""
    s = symbols.sym
    offsets, weights, ok = sigma_offsets(P, s["kappa"])
    D = ca.horzcat(ca.SX.zeros(x.shape), *offsets[1:])
    Y = fns.for_filter("ukf").increment_columns(len(offsets))(t, dt, x, D, s["u"], s["p"])  # split only at an event
    moved = [Y[:, i] for i in range(len(offsets))]
    mean = _weighted_mean(moved, weights)
    deviations = [y - mean for y in moved]
    return (x + mean, _sigma_covariance(weights, deviations, process_noise(symbols, fns, Q, x, t, dt)), ok,
            weights, [ca.SX.zeros(x.shape)] + offsets[1:], deviations)


def ukf_update_expr(symbols: Symbols, fns: ModelFunctions, name: str, msym: dict, wrap, x, P, t):
    s = symbols.sym
    mask = msym["mask"]
    L, weights, ok = sigma_factor(P, s["kappa"])
    points, deviations = sigma_columns(x, L), None
    if fns.config.precision == "float":      # the offsets themselves, not (x + d_i) - x rounded
        offsets, weights, ok = sigma_offsets(P, s["kappa"])
        deviations = [ca.SX.zeros(x.shape)] + offsets[1:]
        points = [x] + [x + d for d in offsets[1:]]
    if deviations is None:          # one called function of the points (the host library's lanes)
        Z = fns.h_at_points(name, sigma_columns)(t, x, ca.tril(L), s["u"], s["p"], msym["q"])
        predicted = [Z[:, i] for i in range(len(points))]
    else:
        h = measurement_function(symbols.model, name)            # inlined: the points share terms (CSE)
        predicted = [h(t, pt, s["u"], s["p"], msym["q"]) for pt in points]
    z_pred = _weighted_mean(predicted, weights, wrap)
    dz = [mask * _angle_difference(zi, z_pred, wrap) for zi in predicted]
    dx = deviations if deviations is not None else [pt - x for pt in points]
    R = masked_noise(msym["R"], mask)
    S = _sigma_covariance(weights, dz, R)
    Pxz = _weighted_products(weights, dx, dz)
    L, ok_s = linalg.cholesky(S)
    # With U = L^-1 Pxz^T: K y = U^T L^-1 y and K S K^T = U^T U (better conditioned than forming K)
    U = linalg.solve_lower(L, Pxz.T)
    y = innovation(msym["z"], z_pred, mask, wrap)
    x_new = x + U.T @ linalg.solve_lower(L, y)
    UtU = linalg.gram(U)
    P_new = linalg.symmetric(P.shape[0], lambda i, j: linalg.symmetric_part(P, i, j) - UtU[i, j])
    nis = ca.sumsqr(linalg.solve_lower(L, y))                 # y^T S^-1 y, for the gate
    return x_new, P_new, y, S, ok * ok_s, nis


def ukf_kernels(model: Model, symbols: Symbols, fns: ModelFunctions) -> Family:
    s = symbols.sym
    qsym, qarg = noise_symbols(model)
    Q = qsym.get("Q", s["Q"])
    x_pred, P_pred, ok_pred = ukf_predict_expr(symbols, fns, s["x"], s["P"], s["t"], s["dt"], Q)
    status = predict_status(ok_pred)
    status = linalg.select(s["kappa"] + model.nx > 0, status, STATUS_DOMAIN)
    kernels = [make_kernel("ukf_predict", _predict_doc(model, "UKF", "2n+1 sigma points, eq (1)-(3)"),
                       symbols, qsym, qarg, ["t", "dt", "x", "P", "u", "p", "Q", "kappa"],
                       [("x", x_pred), ("P", P_pred), ("status", status)])]
    for name, meas in model.measurements.items():
        msym, marg = symbols.measurement(name)
        upd = ukf_update_expr(symbols, fns, name, msym, meas.wrap, s["x"], s["P"], s["t"])
        kernels.append(make_kernel(
            f"ukf_update_{name}", f"UKF update with measurement '{name}' at time t (sigma points redrawn, masked).",
            symbols, msym, marg, UPDATE_INPUTS + ["kappa"],
            update_outputs(upd, s["x"], s["P"], msym["gate"], msym["mask"],
                           update_inputs_finite(symbols))))
        kernels.append(compose_step(f"ukf_step_{name}", kernels[0], kernels[-1]))
    x_pred, P_pred, ok_pred, weights, offsets, moved = ukf_propagation(symbols, fns, s["x"], s["P"], s["t"],
                                                                       s["dt"], Q)
    kernels.append(smooth_kernel("ukf_smooth", "Unscented RTS smoother (Sarkka 2008): one backward step from step "
                                 "k + 1 to k (2n+1 sigma points of x, P at step k).", symbols, qsym, qarg,
                                 ["t", "dt", "x", "P", "u", "p", "Q", "kappa"],
                                 (x_pred, P_pred, cross_covariance(weights, offsets, moved),
                                  ok_pred * (s["kappa"] + model.nx > 0))))
    return Family(kernels, [filter_spec("ukf", "ukf", kernels, model.measurements, defaults={"kappa": 0.0},
                                        smooth="ukf_smooth")])


register_family("ekf", ekf_kernels, options=(IteratedOptions, LockstepOptions))
register_family("ukf", ukf_kernels, long_compile=True, options=(UkfOptions,))      # f_d at the sigma points

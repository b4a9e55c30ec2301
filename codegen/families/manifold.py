"""Manifold filters for any model with unit-quaternion states: a multiplicative (error-state) EKF
and a manifold UKF, generated from the model's own equations.

Families ``"mekf"`` and ``"mukf"`` (filters of the same names). A model declares its quaternions
with ``Model.quaternion_state`` (scalar-last, unit norm) beside ordinary states; nothing else.

**State space.** x holds each quaternion as four numbers; the filters' covariance P lives in
*error coordinates* δ (dimension ``Model.n_error`` = nx - one per quaternion): three components
(a rotation vector, rad) per quaternion, one per ordinary state. The chart is

    retraction   x ⊞ δ:  q = q̂ ⊗ Exp(δθ)            ordinary states: x̂ + δ
    local coords x ⊟ x̂:  δθ = Log(q̂⁻¹ ⊗ q)           ordinary states: x - x̂

with ⊗ the Hamilton product (``quaternion.hamilton``), Exp the exponential map of a rotation
vector (``quaternion.rotvec_to_quaternion``) and Log its inverse (shorter rotation). The error is
therefore a *body-frame* (right) perturbation — Solà, "Quaternion kinematics for the error-state
Kalman filter" (2017), eq (177) local error; Markley, "Attitude error representations for
Kalman filtering", JGCD 26(2) 2003, with the rotation vector as the error parametrisation.

**Prediction.** The mean is the model's RK4 step f_d (``codegen/discretize.py``) followed by a
projection of every quaternion onto the unit sphere (q / |q|). MEKF: P⁻ = F P Fᵀ + Q_d with
F = ∂/∂δ [f_d(x̂ ⊞ δ) ⊟ f_d(x̂)] at δ = 0, derived by CasADi through the retraction. Process
noise as the Kalman family (``kalman.process_noise``), in error coordinates: an additive
n_error x n_error Q gives Q_d = Q dt; a model with ``noise()`` gives Q_d = G Q Gᵀ dt with
G = ∂(x ⊟ x̂)/∂x · ∂f/∂w at the step start.

**Update (MEKF).** H = ∂h(x̂ ⊞ δ)/∂δ at δ = 0 (CasADi); with S = L Lᵀ and U = L⁻¹ H P,
δ̂ = K y = Uᵀ L⁻¹ y and P⁺ = P - K S Kᵀ = P - Uᵀ U (lower triangle, mirrored); then
the multiplicative reset x̂⁺ = x̂ ⊞ δ̂ (quaternion renormalised against round-off). The
covariance is *not* transported to the reset point (the first-order reset of Lefferts, Markley &
Shuster 1982, as in paper 000); the omitted term is O(|δθ̂| P).

**UKF.** 2 n_e + 1 sigma points δ_i = 0, ±columns of chol((n_e + κ) P) (Julier's weights, as the
Kalman UKF), mapped through the retraction χ_i = x̂ ⊞ δ_i. Prediction: χ_i through f_d, the mean
of each quaternion by the eigenvector method (Markley et al., "Averaging quaternions", JGCD 30(4)
2007; no LAPACK, ``quaternion_filters.quaternion_mean``), ordinary states by the weighted mean,
residuals χ_i⁺ ⊟ x̄ in error coordinates. Update: sigma points redrawn from (x̂, P), the
measurement's sigma values as the Kalman UKF (angle outputs wrapped), residuals of the state
are the offsets δ_i exactly, correction by the retraction.

Both: masks, chi-square gates, the input contract and status codes of every filter
(``kernels.update_outputs``): NaN/Inf input -> SYMKF_ERR_NONFINITE, a quaternion of the input
state whose norm is off 1 by more than :data:`QUATERNION_NORM_TOLERANCE` -> SYMKF_ERR_DOMAIN,
a non-PSD P or a failed factorisation -> SYMKF_ERR_NOT_PD; x and P unchanged on any failure.
"""
from __future__ import annotations

import casadi as ca

from symkf.models import quaternion as quat
from symkf.models.base import Model
from .. import linalg
from ..discretize import FUNCTION_OPTIONS, measurement_function
from ..kernels import (ModelFunctions, Symbols, all_finite, compose_step, filter_spec, innovation, make_kernel,
                       masked_finite, masked_noise, register_family, update_status, gated)
from ..spec import STATUS_DOMAIN, STATUS_NONFINITE, STATUS_NOT_PD, Arg, Family
from .kalman import UPDATE_INPUTS, _angle_difference, _predict_doc, _weighted_mean, noise_symbols, sigma_points
from .quaternion_filters import quaternion_mean

#: An input state whose quaternion norm differs from 1 by more than this is SYMKF_ERR_DOMAIN.
QUATERNION_NORM_TOLERANCE = 1e-6
#: Default UKF scaling: κ = 0 as the Kalman UKF (weights 0 and 1/(2 n_e)).
DEFAULT_KAPPA = 0.0

_INLINE = FUNCTION_OPTIONS
_CALLED = dict(FUNCTION_OPTIONS, never_inline=True)


# ---------------------------------------------------------------------- the chart
class Chart:
    """The model's state space as a product of unit-quaternion spheres and R^k: ⊞, ⊟, projection."""

    def __init__(self, model: Model):
        self.n, self.n_error = model.nx, model.n_error
        self.quaternions = [(qs.index, qs.error_index) for qs in model.quaternions]
        in_quaternion = {qs.index + k for qs in model.quaternions for k in range(4)}
        ordinary = [i for i in range(self.n) if i not in in_quaternion]
        # ordinary state i -> its error index: i minus one per quaternion before it
        self.ordinary = [(i, i - sum(1 for qi, _ in self.quaternions if qi < i)) for i in ordinary]

    def _assemble(self, n: int, quaternion_parts, ordinary_parts) -> ca.SX:
        rows = [None] * n
        for start, part in quaternion_parts:
            for k in range(part.shape[0]):
                rows[start + k] = part[k]
        for index, value in ordinary_parts:
            rows[index] = value
        return ca.vertcat(*rows)

    def retract(self, x, delta) -> ca.SX:
        """x ⊞ δ: q ⊗ Exp(δθ) per quaternion (renormalised), x + δ for ordinary states."""
        qs = [(i, quat.normalize(quat.hamilton(x[i:i + 4], quat.rotvec_to_quaternion(delta[e:e + 3]))))
              for i, e in self.quaternions]
        return self._assemble(self.n, qs, [(i, x[i] + delta[e]) for i, e in self.ordinary])

    def local(self, x, x_ref) -> ca.SX:
        """x ⊟ x_ref: Log(q_ref⁻¹ ⊗ q) (rad, shorter rotation) per quaternion, x - x_ref otherwise."""
        qs = [(e, quat.quaternion_to_rotvec(quat.hamilton(quat.conjugate(quat.normalize(x_ref[i:i + 4])),
                                                          quat.normalize(x[i:i + 4]))))
              for i, e in self.quaternions]
        return self._assemble(self.n_error, qs, [(e, x[i] - x_ref[i]) for i, e in self.ordinary])

    def retract_linear(self, x, delta) -> ca.SX:
        """q ⊗ [δθ/2; 1] per quaternion (not renormalised), x + δ otherwise: equal to x ⊞ δ to
        first order at δ = 0, so its Jacobian there is ∂(x ⊞ δ)/∂δ (½ L(q̂) on the vector part)
        without the series and trigonometry of Exp."""
        qs = [(i, quat.hamilton(x[i:i + 4], ca.vertcat(0.5 * delta[e:e + 3], 1))) for i, e in self.quaternions]
        return self._assemble(self.n, qs, [(i, x[i] + delta[e]) for i, e in self.ordinary])

    def local_linear(self, x, x_ref) -> ca.SX:
        """2 vec(q_ref⁻¹ ⊗ q) per quaternion (q and q_ref unit), x - x_ref otherwise: equal to
        x ⊟ x_ref to first order at x = x_ref (Log(q) = 2 vec(q) + O(|δθ|³)), without atan2."""
        qs = [(e, 2 * quat.hamilton(quat.conjugate(x_ref[i:i + 4]), x[i:i + 4])[:3]) for i, e in self.quaternions]
        return self._assemble(self.n_error, qs, [(e, x[i] - x_ref[i]) for i, e in self.ordinary])

    def project(self, x) -> ca.SX:
        """Every quaternion onto the unit sphere (q / |q|); ordinary states unchanged."""
        qs = [(i, quat.normalize(x[i:i + 4])) for i, _ in self.quaternions]
        return self._assemble(self.n, qs, [(i, x[i]) for i, _ in self.ordinary])

    def unit_norm(self, x) -> ca.SX:
        """1 if every quaternion of x has | |q| - 1 | <= QUATERNION_NORM_TOLERANCE, else 0."""
        flag = ca.SX(1)
        for i, _ in self.quaternions:
            flag = flag * (ca.fabs(ca.norm_2(x[i:i + 4]) - 1) <= QUATERNION_NORM_TOLERANCE)
        return flag


class ManifoldFunctions:
    """CasADi Functions of the chart and the model, shared by both families and the NumPy reference."""

    def __init__(self, model: Model, fns: ModelFunctions):
        chart = Chart(model)
        prefix, n, ne = model.name, model.nx, model.n_error
        t, dt = ca.SX.sym("t"), ca.SX.sym("dt")
        x, x_ref, delta = ca.SX.sym("x", n), ca.SX.sym("x_ref", n), ca.SX.sym("delta", ne)
        u, p = ca.SX.sym("u", len(model.inputs)), ca.SX.sym("p", len(model.params))
        self.chart, self.fns = chart, fns
        self.retract = ca.Function(f"{prefix}_retract", [x, delta], [chart.retract(x, delta)], ["x", "delta"], ["x"],
                                   _CALLED)
        self.local = ca.Function(f"{prefix}_local", [x, x_ref], [chart.local(x, x_ref)], ["x", "x_ref"], ["delta"],
                                 _CALLED)
        step = chart.project(fns.fd_inline(t, dt, x, u, p))
        self.step = ca.Function(f"{prefix}_manifold_fd", [t, dt, x, u, p], [step],
                                ["t", "dt", "x", "u", "p"], ["x"], _CALLED)
        # F and H at δ = 0 through the first-order chart (same derivatives, far fewer operations),
        # sparse: structural zeros (e.g. a bias that does not depend on the attitude) cost nothing
        zero = ca.DM.zeros(ne)
        moved = chart.local_linear(chart.project(fns.fd_inline(t, dt, chart.retract_linear(x, delta), u, p)), step)
        F = ca.substitute(ca.jacobian(moved, delta), delta, zero)
        self.step_and_jac = ca.Function(f"{prefix}_manifold_fd_and_jac", [t, dt, x, u, p], [step, F],
                                        ["t", "dt", "x", "u", "p"], ["x", "F"], _CALLED)
        # ∂(x ⊟ x̂)/∂x at x = x̂ (n_e x n): maps state-space noise into error coordinates
        J = ca.substitute(ca.jacobian(chart.local(x, x_ref), x), x, x_ref)
        self.local_jacobian = ca.Function(f"{prefix}_local_jacobian", [x_ref], [ca.densify(J)], ["x"], ["J"], _INLINE)
        self.h, self.jac_h = {}, {}
        for name, meas in model.measurements.items():
            q = ca.SX.sym("q", meas.q.shape[0])
            z = measurement_function(model, name)(t, chart.retract_linear(x, delta), u, p, q)   # h inlined
            H = ca.substitute(ca.jacobian(z, delta), delta, zero)
            self.jac_h[name] = ca.Function(f"{prefix}_manifold_jac_h_{name}", [t, x, u, p, q], [H],
                                           ["t", "x", "u", "p", "q"], ["H"], _CALLED)
            self.h[name] = fns.h[name]

    def mean(self, points: list[ca.SX], weights: list) -> ca.SX:
        """Weighted mean of sigma points on the manifold: eigenvector mean per quaternion (sign of
        the first point's), weighted sum otherwise."""
        chart = self.chart
        w = ca.vertcat(*weights)
        qs = [(i, quaternion_mean(ca.horzcat(*[pt[i:i + 4] for pt in points]), w, points[0][i:i + 4]))
              for i, _ in chart.quaternions]
        linear = sum((wi * pt for wi, pt in zip(weights, points)), ca.SX.zeros(chart.n))
        return chart._assemble(chart.n, qs, [(i, linear[i]) for i, _ in chart.ordinary])


# ---------------------------------------------------------------------- shared pieces
class ManifoldSymbols:
    """P and the additive Q in error coordinates (n_e x n_e); everything else from Symbols."""

    def __init__(self, model: Model, symbols: Symbols):
        ne = model.n_error
        names = _error_names(model)
        qsym, qarg = noise_symbols(model)
        self.sym = {"P": ca.SX.sym("P", ne, ne), "Q": qsym.get("Q", ca.SX.sym("Q", ne, ne))}
        self.arg = {"P": Arg("P", (ne, ne), "error units squared",
                             f"covariance of the error state {names} (rotation vectors in rad)"),
                    "Q": qarg.get("Q", Arg("Q", (ne, ne), "error units squared per second",
                                           f"power spectral density of the error-state noise {names} "
                                           "(discrete: Q dt)"))}
        self.base = symbols

    def measurement(self, name: str):
        msym, marg = self.base.measurement(name)
        return {**self.sym, **msym}, {**self.arg, **marg}


def _error_names(model: Model) -> list[str]:
    names, starts = [], {qs.index: qs.name for qs in model.quaternions}
    skip = 0
    for i, v in enumerate(model.states):
        if skip:
            skip -= 1
            continue
        if i in starts:
            names.append(f"dtheta_{starts[i]} (3)")
            skip = 3
        else:
            names.append(v.name)
    return names


def error_process_noise(model: Model, mf: ManifoldFunctions, symbols: Symbols, Q, x, t, dt):
    """Q_d in error coordinates: Q dt (additive), or G Q Gᵀ dt with G = ∂(x ⊟ x̂)/∂x · ∂f/∂w."""
    if mf.fns.noise_gain is None:
        return Q * dt
    s = symbols.sym
    G = mf.local_jacobian(x) @ mf.fns.noise_gain(t, x, s["u"], s["p"])
    return G @ Q @ G.T * dt


def predict_status(chart: Chart, symbols: Symbols, P, Q, ok, extra=()):
    """NONFINITE for a NaN/Inf input, else DOMAIN for a non-unit quaternion, else NOT_PD unless ok."""
    s = symbols.sym
    finite = all_finite([s["t"], s["dt"], s["x"], P, s["u"], s["p"], Q, *extra])
    status = linalg.select(chart.unit_norm(s["x"]), linalg.select(ok, 0, STATUS_NOT_PD), STATUS_DOMAIN)
    return linalg.select(finite, status, STATUS_NONFINITE)


def predict_kernel(name: str, doc: str, ms: ManifoldSymbols, chart: Chart, x_pred, P_pred, ok, inputs, extra=()):
    s = ms.base.sym
    status = predict_status(chart, ms.base, ms.sym["P"], ms.sym["Q"], ok, extra)
    return make_kernel(name, doc, ms.base, ms.sym, ms.arg, inputs,
                       [("x", linalg.select(status == 0, x_pred, s["x"])),
                        ("P", linalg.select(status == 0, P_pred, ms.sym["P"])), ("status", status)])


def inputs_finite(ms: ManifoldSymbols, msym: dict, extra=()) -> ca.SX:
    """Every input of an update is finite (z only where the mask uses it)."""
    s = ms.base.sym
    return all_finite([s["x"], ms.sym["P"], s["u"], s["p"], msym["q"], msym["mask"], msym["R"], msym["gate"],
                       *extra]) * masked_finite(msym["z"], msym["mask"])


def update_outputs(chart: Chart, update, x_old, P_old, msym):
    """x, P (unchanged unless the update succeeded and passed the gate), y, S, status; a non-unit
    input quaternion is SYMKF_ERR_DOMAIN (after NONFINITE)."""
    x_new, P_new, y, S, ok, nis, finite = update
    unit = chart.unit_norm(x_old)
    is_gated = gated(msym["gate"], msym["mask"], nis)
    keep = ok * (1 - is_gated) * finite * unit
    status = update_status(ok, is_gated, finite)
    status = linalg.select(finite * (1 - unit), STATUS_DOMAIN, status)
    x_out, P_out = (linalg.select(keep, new, old) for new, old in ((x_new, x_old), (P_new, P_old)))
    return [("x", x_out), ("P", P_out), ("y", y), ("S", S), ("status", status)]


# ---------------------------------------------------------------------- MEKF
def mekf_update_expr(mf: ManifoldFunctions, ms: ManifoldSymbols, name: str, msym: dict, wrap):
    s, P = ms.base.sym, ms.sym["P"]
    t, x = s["t"], s["x"]
    mask = msym["mask"]
    z_pred = mf.h[name](t, x, s["u"], s["p"], msym["q"])
    H = ca.diag(mask) @ mf.jac_h[name](t, x, s["u"], s["p"], msym["q"])
    R = masked_noise(msym["R"], mask)
    y = innovation(msym["z"], z_pred, mask, wrap)
    HP = H @ P                                       # sparse H: structural zeros cost nothing
    HPH = linalg.sandwich(H, P)
    S = linalg.symmetric(R.shape[0], lambda i, j: HPH[i, j] + linalg.symmetric_part(R, i, j))
    L, ok = linalg.cholesky(S)
    # With U = L⁻¹ H P: K = Uᵀ L⁻¹, K y = Uᵀ L⁻¹ y and K S Kᵀ = Uᵀ U (as the Kalman EKF and UKF)
    U = linalg.solve_lower(L, HP)
    white = linalg.solve_lower(L, y)
    x_new = mf.retract(x, U.T @ white)               # multiplicative reset
    UtU = linalg.gram(U)
    P_new = linalg.symmetric(P.shape[0], lambda i, j: linalg.symmetric_part(P, i, j) - UtU[i, j])
    nis = ca.sumsqr(white)
    finite = inputs_finite(ms, msym)
    return x_new, P_new, y, S, ok * linalg.psd_flag(P), nis, finite


def mekf_kernels(model: Model, symbols: Symbols, fns: ModelFunctions) -> Family:
    _require_quaternion(model, "mekf")
    mf, ms = ManifoldFunctions(model, fns), ManifoldSymbols(model, symbols)
    s, P, Q = symbols.sym, ms.sym["P"], ms.sym["Q"]
    x_pred, F = mf.step_and_jac(s["t"], s["dt"], s["x"], s["u"], s["p"])
    FPF, Qd = linalg.sandwich(F, P), error_process_noise(model, mf, symbols, Q, s["x"], s["t"], s["dt"])
    P_pred = linalg.symmetric(P.shape[0], lambda i, j: FPF[i, j] + linalg.symmetric_part(Qd, i, j))
    doc = _predict_doc(model, "Multiplicative EKF", "RK4 then |q| = 1; P = F P F^T + Q_d, F = d(f_d(x (+) d) (-) "
                       "f_d(x))/dd in error coordinates")
    predict = predict_kernel("mekf_predict", doc, ms, mf.chart, x_pred, P_pred, linalg.psd_flag(P),
                             ["t", "dt", "x", "P", "u", "p", "Q"])
    kernels = [predict]
    for name, meas in model.measurements.items():
        msym, marg = ms.measurement(name)
        upd = mekf_update_expr(mf, ms, name, msym, meas.wrap)
        kernels.append(make_kernel(
            f"mekf_update_{name}", f"Multiplicative EKF update with '{name}': H = dh(x (+) d)/dd, P - K S K^T, "
            "reset x = x (+) K y (masked, gated).", symbols, msym, marg, UPDATE_INPUTS,
            update_outputs(mf.chart, upd, s["x"], P, msym)))
        kernels.append(compose_step(f"mekf_step_{name}", predict, kernels[-1]))
    return Family(kernels, [filter_spec("mekf", "manifold_ekf", kernels, model.measurements)])


# ---------------------------------------------------------------------- manifold UKF
def mukf_predict_expr(model: Model, mf: ManifoldFunctions, ms: ManifoldSymbols):
    s, P = ms.base.sym, ms.sym["P"]
    offsets, weights, ok = sigma_points(ca.SX.zeros(P.shape[0]), P, s["kappa"])
    propagated = [mf.step(s["t"], s["dt"], mf.retract(s["x"], d), s["u"], s["p"]) for d in offsets]
    x_mean = mf.mean(propagated, weights)
    residuals = [mf.local(pt, x_mean) for pt in propagated]
    P_pred = sum((w * r @ r.T for w, r in zip(weights, residuals)), ca.SX.zeros(P.shape)) + \
        error_process_noise(model, mf, ms.base, ms.sym["Q"], s["x"], s["t"], s["dt"])
    return x_mean, linalg.symmetrize(P_pred), ok


def mukf_update_expr(mf: ManifoldFunctions, ms: ManifoldSymbols, name: str, msym: dict, wrap):
    s, P = ms.base.sym, ms.sym["P"]
    t, x, mask = s["t"], s["x"], msym["mask"]
    offsets, weights, ok = sigma_points(ca.SX.zeros(P.shape[0]), P, s["kappa"])
    predicted = [mf.h[name](t, mf.retract(x, d), s["u"], s["p"], msym["q"]) for d in offsets]
    z_pred = _weighted_mean(predicted, weights, wrap)
    dz = [mask * _angle_difference(zi, z_pred, wrap) for zi in predicted]
    R = masked_noise(msym["R"], mask)
    S = linalg.symmetrize(sum((w * d @ d.T for w, d in zip(weights, dz)), ca.SX.zeros(R.shape)) + R)
    Pxz = sum((w * a @ b.T for w, a, b in zip(weights, offsets, dz)), ca.SX.zeros(P.shape[0], R.shape[0]))
    L, ok_s = linalg.cholesky(S)
    U = linalg.solve_lower(L, Pxz.T)                 # K y = Uᵀ L⁻¹ y, K S Kᵀ = Uᵀ U
    y = innovation(msym["z"], z_pred, mask, wrap)
    x_new = mf.retract(x, U.T @ linalg.solve_lower(L, y))
    P_new = linalg.symmetrize(P - U.T @ U)
    nis = ca.sumsqr(linalg.solve_lower(L, y))
    finite = inputs_finite(ms, msym, [s["kappa"]])
    return x_new, P_new, y, S, ok * ok_s, nis, finite


def mukf_kernels(model: Model, symbols: Symbols, fns: ModelFunctions) -> Family:
    _require_quaternion(model, "mukf")
    mf, ms = ManifoldFunctions(model, fns), ManifoldSymbols(model, symbols)
    s = symbols.sym
    x_pred, P_pred, ok = mukf_predict_expr(model, mf, ms)
    ok = ok * (s["kappa"] + model.n_error > 0)
    doc = _predict_doc(model, "Manifold UKF", f"{2 * model.n_error + 1} sigma points x (+) d_i, quaternion "
                       "eigenvector mean, residuals in error coordinates")
    predict = predict_kernel("mukf_predict", doc, ms, mf.chart, x_pred, P_pred, ok,
                             ["t", "dt", "x", "P", "u", "p", "Q", "kappa"], [s["kappa"]])
    kernels = [predict]
    for name, meas in model.measurements.items():
        msym, marg = ms.measurement(name)
        upd = mukf_update_expr(mf, ms, name, msym, meas.wrap)
        kernels.append(make_kernel(
            f"mukf_update_{name}", f"Manifold UKF update with '{name}': sigma points x (+) d_i redrawn, correction "
            "by the retraction (masked, gated).", symbols, msym, marg, UPDATE_INPUTS + ["kappa"],
            update_outputs(mf.chart, upd, s["x"], ms.sym["P"], msym)))
        kernels.append(compose_step(f"mukf_step_{name}", predict, kernels[-1]))
    return Family(kernels, [filter_spec("mukf", "manifold_ukf", kernels, model.measurements,
                                        defaults={"kappa": DEFAULT_KAPPA})])


def _require_quaternion(model: Model, family: str) -> None:
    if not model.quaternions:
        raise ValueError(f"filter family '{family}' is for models with quaternion_state(); model '{model.name}' "
                         "has none (use 'ekf' / 'ukf')")


register_family("mekf", mekf_kernels)
register_family("mukf", mukf_kernels)

"""What the manifold filters share (MEKF ``mekf.py``, manifold UKF ``mukf.py``, the sampled
UKFs ``quaternion_filters.py``): the CasADi Functions of the chart and the model
(:class:`ManifoldFunctions`), P and Q in error coordinates (:class:`ManifoldSymbols`), the
process noise, the predict kernel, the measurement input and the update's outputs and statuses.

**State space.** x holds each quaternion as four numbers; the filters' covariance P lives in
*error coordinates* δ (dimension ``Model.n_error``), the chart of ``chart.py``. A quaternion
measurement (``Model.measurement(..., quaternion=True)``) has its innovation z ⊟ ẑ in the same
chart; a measurement with its own noise v (``Model.measurement_noise``) has R = cov(v), entering
as D R Dᵀ with D = ∂(h(x̂, v) ⊟ h(x̂, 0))/∂v.

**Prediction.** The mean is the model's RK4 step f_d (``codegen/discretize.py``), or its exact
step, followed by a projection of every quaternion onto the unit sphere (q / |q|). Process
noise as the Kalman family (``kalman.process_noise``), in error coordinates: an additive
n_error x n_error Q gives Q_d = Q dt; a model with ``noise()`` gives Q_d = G Q Gᵀ dt with
G = ∂(x ⊟ x̂)/∂x · ∂f/∂w at the step start; held noise Q_d = G_d (Q/dt) G_dᵀ (paper 000 eq (29)).

Every manifold filter: masks, chi-square gates, the input contract and status codes of every filter
(``framework.update_outputs``): NaN/Inf input -> SYMKF_ERR_NONFINITE, a quaternion of the input
state whose norm is off 1 by more than :data:`chart.QUATERNION_NORM_TOLERANCE` -> SYMKF_ERR_DOMAIN,
a non-PSD P or a failed factorisation -> SYMKF_ERR_NOT_PD; x and P unchanged on any failure.

**Input checks.** The kernels of these families do not test their inputs for NaN/Inf: every
caller does, before a kernel runs, with the same rule (every input finite; z only where its mask
is > 0.5 when z and mask have one entry per component): the C wrappers and run loops
(``codegen/c_backend/api.py``) and the CasADi-VM backend (``runtime/backends.py``). An in-kernel test
would repeat theirs at one multiply-add per input entry (about 150 entries, 0.36k of the MARG
step's 3k operations) on every sample.
"""
from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from symkf.models.base import Model
from .. import linalg
from ..discretize import (CALLED_OPTIONS, FUNCTION_OPTIONS, continuous_dynamics, discrete_dynamics, exact_step_function,
                          measurement_function, noisy_measurement_function)
from ..model_functions import ModelFunctions, Symbols
from ..spec import STATUS_ARGS, STATUS_DOMAIN, STATUS_NOT_PD, Arg
from .chart import Chart, ManifoldOptions, quaternion_mean
from .framework import gated, innovation, make_kernel, update_status
from .kalman import _weighted_mean, noise_symbols

#: A quaternion *measurement* is normalised if | |z| - 1 | <= this, SYMKF_ERR_DOMAIN otherwise.
MEASUREMENT_NORM_TOLERANCE = 1e-3

_INLINE = FUNCTION_OPTIONS


class ManifoldFunctions:
    """CasADi Functions of the chart and the model, shared by every manifold family and the NumPy
    reference: retraction, local coordinates, the step f_d (RK4 or the model's exact step) with its
    error-state transition F, the held-noise gain G_d, and per measurement h, its residual in the
    chart (quaternion measurements), H = ∂r/∂δ and D = ∂r/∂v (measurement noise v)."""

    def __init__(self, model: Model, fns: ModelFunctions):
        self.options = ManifoldOptions.for_model(model, fns.config)
        chart = Chart(model, self.options)
        prefix, n, ne = model.name, model.nx, model.n_error
        t, dt = ca.SX.sym("t"), ca.SX.sym("dt")
        x, x_ref, delta = ca.SX.sym("x", n), ca.SX.sym("x_ref", n), ca.SX.sym("delta", ne)
        u, p, w = ca.SX.sym("u", len(model.inputs)), ca.SX.sym("p", len(model.params)), ca.SX.sym("w", len(model.noises))
        self.chart, self.fns, self.model = chart, fns, model
        self.retract = ca.Function(f"{prefix}_retract", [x, delta], [chart.retract(x, delta)], ["x", "delta"], ["x"],
                                   CALLED_OPTIONS)
        self.local = ca.Function(f"{prefix}_local", [x, x_ref], [chart.local(x, x_ref)], ["x", "x_ref"], ["delta"],
                                 CALLED_OPTIONS)
        self.fd_noisy = self._noisy_step(model, fns)
        fd = (lambda *a: self.fd_noisy(*a, ca.DM.zeros(len(model.noises)))) if self.options.step == "exact" \
            else fns.fd_inline
        step = chart.project(fd(t, dt, x, u, p))
        self.step = ca.Function(f"{prefix}_manifold_fd", [t, dt, x, u, p], [step],
                                ["t", "dt", "x", "u", "p"], ["x"], CALLED_OPTIONS)
        # F and H at δ = 0 through the first-order chart (same derivatives, far fewer operations),
        # sparse: structural zeros (e.g. a bias that does not depend on the attitude) cost nothing
        zero = ca.DM.zeros(ne)
        if self.options.transition == "series":
            F = self._series_transition(model, t, dt, x, u, p, delta)
        else:
            F = self._transition(fd(t, dt, x, u, p), fd(t, dt, chart.retract_linear(x, delta), u, p), step, delta)
        self.step_and_jac = ca.Function(f"{prefix}_manifold_fd_and_jac", [t, dt, x, u, p], [step, F],
                                        ["t", "dt", "x", "u", "p"], ["x", "F"], _INLINE)
        # ∂(x ⊟ x̂)/∂x at x = x̂ (n_e x n): maps state-space noise into error coordinates
        J = ca.substitute(ca.jacobian(chart.local(x, x_ref), x), x, x_ref)
        self.local_jacobian = ca.Function(f"{prefix}_local_jacobian", [x_ref], [ca.densify(J)], ["x"], ["J"], _INLINE)
        if self.options.noise == "held":    # G_d = ∂(f_d(x̂, w) ⊟ f_d(x̂, 0))/∂w at w = 0
            G = ca.jacobian(chart.local_linear(chart.project(self.fd_noisy(t, dt, x, u, p, w)), step), w)
            G = ca.substitute(G, w, ca.DM.zeros(w.shape[0]))
            self.held_noise_gain = ca.Function(f"{prefix}_held_noise_gain", [t, dt, x, u, p], [ca.densify(G)],
                                               ["t", "dt", "x", "u", "p"], ["G"], _INLINE)
        self.h, self.h_inline, self.jac_h, self.h_noisy, self.noise_jac = {}, {}, {}, {}, {}
        for name, meas in model.measurements.items():
            self._measurement(model, name, meas, t, x, u, p, delta, zero)

    def _transition(self, v, moved, step, delta) -> ca.SX:
        """F = ∂/∂δ [local_linear(project(f_d(x̂ ⊞ δ)), x̂⁺)] at δ = 0, x̂⁺ = project(v), v = f_d(x̂).
        The projection is not differentiated: local_linear(·, x̂⁺) is linear and maps x̂⁺'s own
        direction to 0, so through q / |q| its derivative is its own divided by |v_q| (each
        quaternion's rows); the same F to round-off, without the derivative of the norm."""
        F = ca.substitute(ca.jacobian(self.chart.local_linear(moved, step), delta), delta, ca.DM.zeros(delta.shape[0]))
        for i, e in self.chart.quaternions:
            F[e:e + 3, :] = F[e:e + 3, :] / ca.norm_2(v[i:i + 4])
        return F

    def error_rate_matrix(self, model: Model, t, x, u, p, delta) -> ca.SX:
        """A = ∂δ̇/∂δ at δ = 0 (n_e x n_e, sparse): the rate of the first-order error
        δ = local_linear(x, x̂) along two solutions of dx/dt = f, x = x̂ ⊞ δ and x̂:
        δ̇ = ∂L/∂x f(x) + ∂L/∂x̂ f(x̂) (noise-free f, inputs held). For the right error of
        dq/dt = ½ q ⊗ [ω; 0] it is -[ω]× in the attitude block (Solà 2017, eq (237))."""
        x_any, x_ref = ca.SX.sym("x_any", x.shape[0]), ca.SX.sym("x_ref", x.shape[0])
        f = continuous_dynamics(model)
        zero_w = ca.DM.zeros(len(model.noises))
        L = self.chart.local_linear(x_any, x_ref)
        rate = ca.jtimes(L, x_any, f(t, x_any, u, p, zero_w)) + ca.jtimes(L, x_ref, f(t, x_ref, u, p, zero_w))
        rate = ca.substitute(ca.substitute(rate, x_any, self.chart.retract_linear(x_ref, delta)), x_ref, x)
        A = ca.substitute(ca.jacobian(rate, delta), delta, ca.DM.zeros(delta.shape[0]))
        return self._invariant_attitudes(A, [t, x, u, p], x)

    def _invariant_attitudes(self, A: ca.SX, args: list, x: ca.SX, draws: int = 4) -> ca.SX:
        """A with each quaternion q̂ it does not depend on *on the unit sphere* replaced by the
        identity [0, 0, 0, 1]. The chart's expressions carry q̂ as products like q̂* ⊗ q̂ = |q̂|²
        that CasADi cannot cancel; for group-affine dynamics (dq/dt = ½ q ⊗ ω, Barrau & Bonnabel,
        "The invariant extended Kalman filter as a stable observer", IEEE TAC 62(4) 2017) the error
        dynamics are the same at every attitude, and evaluated at the identity they are the short
        closed form (-[ω]×, ...). Independence is tested by evaluation: A at ``draws`` random
        arguments (fixed seed) against A with that quaternion redrawn at random, to 1e-12 relative;
        a polynomial in q̂ that passes at random points is constant on the sphere (Schwartz-Zippel)."""
        rng = np.random.default_rng(20171)
        evaluate = ca.Function("A", args, [A])
        for i, _ in self.chart.quaternions:
            same = True
            for _ in range(draws):
                values = [rng.normal(size=a.shape[0]) for a in args]
                values[1] = self._random_unit_quaternions(values[1], rng)
                moved = values[1].copy()
                moved[i:i + 4] = self._unit(rng.normal(size=4))
                a, b = (np.array(evaluate(*v)) for v in (values, [*values[:1], moved, *values[2:]]))
                scale = max(1.0, float(np.max(np.abs(a))))
                same = same and bool(np.all(np.isfinite(a))) and float(np.max(np.abs(a - b))) <= 1e-12 * scale
            if same:
                A = ca.substitute(A, x[i:i + 4], ca.DM([0, 0, 0, 1]))
        return A

    def _random_unit_quaternions(self, x: np.ndarray, rng) -> np.ndarray:
        for i, _ in self.chart.quaternions:
            x[i:i + 4] = self._unit(rng.normal(size=4))
        return x

    @staticmethod
    def _unit(v: np.ndarray) -> np.ndarray:
        return v / np.linalg.norm(v)

    def _series_transition(self, model: Model, t, dt, x, u, p, delta) -> ca.SX:
        """F = I + A dt + (A dt)²/2 (:meth:`error_rate_matrix`; ManifoldOptions.transition "series")."""
        Adt = self.error_rate_matrix(model, t, x, u, p, delta) * dt
        return ca.SX.eye(delta.shape[0]) + Adt + 0.5 * (Adt @ Adt)

    def _noisy_step(self, model: Model, fns: ModelFunctions) -> ca.Function | None:
        """f_d(t, dt, x, u, p, w) with the noises held over the step (exact step or RK4), or None."""
        if self.options.step == "exact":
            made = exact_step_function(model)
        elif self.options.noise == "held":
            made = discrete_dynamics(model, fns.config.rk4_substeps, "rk4", bool(fns.config.get("split_events", True)))
        else:
            return None
        return ca.Function(f"{model.name}_manifold_fd_noisy", made.sx_in(), made.call(made.sx_in()),
                           ["t", "dt", "x", "u", "p", "w"], ["x"], CALLED_OPTIONS)

    def _measurement(self, model, name, meas, t, x, u, p, delta, zero):
        q = ca.SX.sym("q", meas.q.shape[0])
        h, inline = self.fns.h[name], measurement_function(model, name)
        z_hat = inline(t, x, u, p, q)
        # first-order chart (same H, fewer operations), h inlined (CasADi differentiates its expressions)
        z = inline(t, self.chart.retract_linear(x, delta), u, p, q)
        r = self.chart.quaternion_local_linear(z, z_hat) if meas.quaternion else z
        H = ca.substitute(ca.jacobian(r, delta), delta, zero)
        self.jac_h[name] = ca.Function(f"{model.name}_manifold_jac_h_{name}", [t, x, u, p, q], [H],
                                       ["t", "x", "u", "p", "q"], ["H"], _INLINE)
        self.h[name] = h
        self.h_inline[name] = inline
        if meas.v.shape[0]:
            v = ca.SX.sym("v", meas.v.shape[0])
            noisy = noisy_measurement_function(model, name)
            self.h_noisy[name] = ca.Function(f"{model.name}_h_{name}_noisy", [t, x, u, p, q, v],
                                             [noisy(t, x, u, p, q, v)], ["t", "x", "u", "p", "q", "v"], ["z"], CALLED_OPTIONS)
            z_v = noisy(t, x, u, p, q, v)
            r_v = self.chart.quaternion_local_linear(z_v, z_hat) if meas.quaternion else z_v
            D = ca.substitute(ca.jacobian(r_v, v), v,
                              ca.DM.zeros(v.shape[0]))
            self.noise_jac[name] = ca.Function(f"{model.name}_manifold_noise_jac_{name}", [t, x, u, p, q],
                                               [ca.densify(D)], ["t", "x", "u", "p", "q"], ["D"], _INLINE)

    def residual(self, name: str, z, z_ref) -> ca.SX:
        """z ⊟ z_ref of a measurement: in the chart for a quaternion measurement, z - z_ref otherwise."""
        meas = self.model.measurements[name]
        return self.chart.quaternion_local(z, z_ref) if meas.quaternion else z - z_ref

    def measurement_noise(self, name: str, R, t, x, u, p, q) -> ca.SX:
        """R in innovation coordinates: D R Dᵀ for a measurement with its own noise v, else R."""
        return self.noise_jac[name](t, x, u, p, q) @ R @ self.noise_jac[name](t, x, u, p, q).T \
            if name in self.noise_jac else R

    def mean(self, points: list[ca.SX], weights: list) -> ca.SX:
        """Weighted mean of sigma points on the manifold: eigenvector mean per quaternion (sign of
        the first point's), weighted sum otherwise."""
        chart = self.chart
        w = ca.vertcat(*weights)
        qs = [(i, quaternion_mean(ca.horzcat(*[pt[i:i + 4] for pt in points]), w, points[0][i:i + 4]))
              for i, _ in chart.quaternions]
        linear = sum((wi * pt for wi, pt in zip(weights, points)), ca.SX.zeros(chart.n))
        return chart._assemble(chart.n, qs, [(i, linear[i]) for i, _ in chart.ordinary])

    def measurement_mean(self, name: str, points: list[ca.SX], weights: list) -> ca.SX:
        """Mean of predicted measurements: eigenvector mean of a quaternion measurement, else the
        weighted mean (angles on the circle)."""
        meas = self.model.measurements[name]
        if meas.quaternion:
            return quaternion_mean(ca.horzcat(*points), ca.vertcat(*weights), points[0])
        return _weighted_mean(points, weights, meas.wrap)


def continuous_functions(model: Model) -> tuple[ca.Function, ca.Function]:
    """f(t, x, u, p) and ∂f/∂x (noise-free), for the NumPy reference's error dynamics."""
    f = continuous_dynamics(model)
    args = [model.t, model.x, model.u, model.p]
    xdot = f(*args, ca.DM.zeros(len(model.noises)))
    return (ca.Function(f"{model.name}_f", args, [xdot], _INLINE),
            ca.Function(f"{model.name}_jac_f", args, [ca.jacobian(xdot, model.x)], _INLINE))


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
    """Q_d in error coordinates: Q dt (additive), G Q Gᵀ dt with G = ∂(x ⊟ x̂)/∂x · ∂f/∂w (continuous),
    or G_d (Q/dt) G_dᵀ (held; dt <= 0 is refused by :func:`predict_status`)."""
    s = symbols.sym
    if mf.options.noise == "held":
        G = mf.held_noise_gain(t, dt, x, s["u"], s["p"])
        return G @ (Q / linalg.guarded(dt, dt > 0)) @ G.T
    if mf.fns.noise_gain is None:
        return Q * dt
    G = mf.local_jacobian(x) @ mf.fns.noise_gain(t, x, s["u"], s["p"])
    return G @ Q @ G.T * dt


def predict_status(mf: ManifoldFunctions, symbols: Symbols, ok, in_domain=1, unit: bool = True):
    """DOMAIN for a non-unit quaternion (unless ``unit`` is False: not tested), dt <= 0 with held
    noise or not ``in_domain`` (a sigma point outside the chart), else NOT_PD unless ok (inputs
    are finite: see "Input checks" above)."""
    s = symbols.sym
    domain = (mf.chart.unit_norm(s["x"]) if unit else 1) * ((s["dt"] > 0) if mf.options.noise == "held" else 1) * in_domain
    return linalg.select(domain, linalg.select(ok, 0, STATUS_NOT_PD), STATUS_DOMAIN)


def predict_kernel(name: str, doc: str, ms: ManifoldSymbols, mf: ManifoldFunctions, x_pred, P_pred, ok, inputs,
                   extra_sym=None, extra_arg=None, in_domain=1):
    status = predict_status(mf, ms.base, ok, in_domain)
    return make_kernel(name, doc, ms.base, {**ms.sym, **(extra_sym or {})}, {**ms.arg, **(extra_arg or {})}, inputs,
                       [("x", x_pred), ("P", P_pred), ("status", status)])     # not written on a failure


@dataclass
class MeasurementInput:
    """One update's measurement as the algebra uses it: z (a quaternion normalised), the mask per
    innovation component, and the flags of the bad-input rules."""

    z: ca.SX
    mask: ca.SX          # per innovation component (a quaternion's one entry repeated 3 times)
    unit: ca.SX          # a used quaternion measurement has | |z| - 1 | <= MEASUREMENT_NORM_TOLERANCE
    valid: ca.SX = 1     # the arguments suit the algorithm (a sequential update: R diagonal), else ARGS
    finite: ca.SX = 1    # inputs finite: always, see "Input checks" in the module docstring


def measurement_input(model: Model, ms: ManifoldSymbols, name: str, msym: dict) -> MeasurementInput:
    """z, the mask per innovation component and the unit-norm flag of a quaternion measurement."""
    meas = model.measurements[name]
    mask, z = msym["mask"], msym["z"]
    if not meas.quaternion:
        return MeasurementInput(z, mask, ca.SX(1))
    use = mask[0] > 0.5
    z_used = linalg.select(use, z, ca.DM([0, 0, 0, 1]))          # a masked NaN enters no arithmetic
    norm = ca.norm_2(z_used)
    unit = (ca.fabs(norm - 1) <= MEASUREMENT_NORM_TOLERANCE)
    return MeasurementInput(z_used / ca.fmax(norm, linalg.TINY), ca.repmat(mask, 3, 1), unit)


def chart_innovation(mf: ManifoldFunctions, name: str, m: MeasurementInput, z_pred, wrap) -> ca.SX:
    """The innovation z ⊟ ẑ, masked components 0 (angles wrapped)."""
    if mf.model.measurements[name].quaternion:
        return m.mask * mf.residual(name, m.z, z_pred)
    return innovation(m.z, z_pred, m.mask, wrap)


def update_outputs(chart: Chart, update, x_old, P_old, msym, m: MeasurementInput | None = None):
    """x, P (the update's, or the inputs when the gate refused it), y, S, status; a non-unit
    input quaternion, a non-unit quaternion measurement or a correction outside the chart is
    SYMKF_ERR_DOMAIN (after NONFINITE). On an error status the outputs are not selected back to
    the inputs: no backend writes a failed kernel's outputs (C ``_eval``, the VM's ``evaluate``),
    so x and P stay unchanged without a select per entry."""
    x_new, P_new, y, S, ok, nis, finite = update[:7]
    in_domain = update[7] if len(update) > 7 else ca.SX(1)
    mask = msym["mask"] if m is None else m.mask
    unit = chart.unit_norm(x_old) * (1 if m is None else m.unit)
    is_gated = gated(msym["gate"], mask, nis)
    used = ca.sum1(mask) > 0
    domain = unit * (1 - used * (1 - in_domain))
    valid = 1 if m is None else m.valid
    status = update_status(ok, is_gated, finite)
    status = linalg.select(finite * (1 - domain), STATUS_DOMAIN, status)
    if not isinstance(valid, int):
        status = linalg.select(finite * (1 - valid), STATUS_ARGS, status)
    x_out, P_out = (linalg.select(is_gated, old, new) for new, old in ((x_new, x_old), (P_new, P_old)))
    return [("x", x_out), ("P", P_out), ("y", y), ("S", S), ("status", status)]



def require_quaternion(model: Model, family: str) -> None:
    if not model.quaternions:
        raise ValueError(f"filter family '{family}' is for models with quaternion_state(); model '{model.name}' "
                         "has none (use 'ekf' / 'ukf')")


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

**Options** (:class:`ManifoldOptions`, codegen config ``manifold_chart/_side/_step/_noise/_update/_transition``, a
model's own in ``Model.codegen_defaults``): the error may instead be the vector part δp of
δq = [δp; √(1 - |δp|²)] (paper 000 eqs (34), (41), (52); half-angle units; |δp| >= 1 is
SYMKF_ERR_DOMAIN), on the left (δq ⊗ q̂, reference frame) instead of the right; the step may be
the model's exact one (``Model.set_discrete_step``) instead of RK4; the process noise may be
*held* over the step inside that step (Q_d = G_d (Q/dt) G_dᵀ, paper 000 eq (29)). A quaternion
measurement (``Model.measurement(..., quaternion=True)``) has its innovation z ⊟ ẑ in the same
chart; a measurement with its own noise v (``Model.measurement_noise``) has R = cov(v), entering
as D R Dᵀ with D = ∂(h(x̂, v) ⊟ h(x̂, 0))/∂v. ``models/attitude.py`` sets paper 000's options;
its separated-noise and augmented UKFs are the families "sukf" and "aukf" of
``quaternion_filters.py``, on these same primitives. ``manifold_run_variants`` lists mask
patterns that get MEKF step and run kernels of their own, the masked components and the gate
folded away (:func:`mekf_run_kernels`; the same results, a larger bundle).

**Prediction.** The mean is the model's RK4 step f_d (``codegen/discretize.py``) followed by a
projection of every quaternion onto the unit sphere (q / |q|). MEKF: P⁻ = F P Fᵀ + Q_d with
F = ∂/∂δ [f_d(x̂ ⊞ δ) ⊟ f_d(x̂)] at δ = 0, derived by CasADi through the retraction (or, with
manifold_transition="series", the series I + A dt + (A dt)²/2 of the continuous error dynamics
A = ∂δ̇/∂δ, also derived by CasADi: :meth:`ManifoldFunctions.error_rate_matrix`). Process
noise as the Kalman family (``kalman.process_noise``), in error coordinates: an additive
n_error x n_error Q gives Q_d = Q dt; a model with ``noise()`` gives Q_d = G Q Gᵀ dt with
G = ∂(x ⊟ x̂)/∂x · ∂f/∂w at the step start.

**Update (MEKF).** H = ∂h(x̂ ⊞ δ)/∂δ at δ = 0 (CasADi); with S = L Lᵀ and U = L⁻¹ H P,
δ̂ = K y = Uᵀ L⁻¹ y and P⁺ = P - K S Kᵀ = P - Uᵀ U (lower triangle, mirrored); then
the multiplicative reset x̂⁺ = x̂ ⊞ δ̂ (quaternion renormalised against round-off). The
covariance is *not* transported to the reset point (the first-order reset of Lefferts, Markley &
Shuster 1982, as in paper 000); the omitted term is O(|δθ̂| P). With ``manifold_update="sequential"``
the same update is m scalar updates in turn (:func:`sequential_update`; a diagonal R). The step
kernel is one expression (:func:`mekf_step_kernel`): inputs checked once, outputs selected once.

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

**Input checks.** The kernels of these families do not test their inputs for NaN/Inf: every
caller does, before a kernel runs, with the same rule (every input finite; z only where its mask
is > 0.5 when z and mask have one entry per component): the C wrappers and run loops
(``codegen/c_backend/api.py``) and the CasADi-VM backend (``runtime/backends.py``). An in-kernel test
would repeat theirs at one multiply-add per input entry (about 150 entries, 0.36k of the MARG
step's 3k operations) on every sample.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import casadi as ca
import numpy as np

from symkf.models import quaternion as quat
from symkf.models.base import Model
from .. import linalg
from ..discretize import (FUNCTION_OPTIONS, continuous_dynamics, discrete_dynamics, exact_step_function, measurement_function,
                          noisy_measurement_function)
from ..kernels import (CANONICAL_ORDER, ModelFunctions, Symbols, compose_step, filter_spec, gated,
                       innovation, make_kernel, masked_noise, register_family, update_status)
from ..spec import (STATUS_ARGS, STATUS_DOMAIN, STATUS_NOT_PD, Arg, CodegenConfig, ConfigError, Family,
                   Kernel, register_options)
from .kalman import UPDATE_INPUTS, _angle_difference, _predict_doc, _weighted_mean, noise_symbols, sigma_points
from .quaternion_filters import quaternion_mean

#: An input state whose quaternion norm differs from 1 by more than this is SYMKF_ERR_DOMAIN.
QUATERNION_NORM_TOLERANCE = 1e-6
#: A quaternion *measurement* is normalised if | |z| - 1 | <= this, SYMKF_ERR_DOMAIN otherwise.
MEASUREMENT_NORM_TOLERANCE = 1e-3
#: Default UKF scaling: κ = 0 as the Kalman UKF (weights 0 and 1/(2 n_e)).
DEFAULT_KAPPA = 0.0

_INLINE = FUNCTION_OPTIONS
_CALLED = dict(FUNCTION_OPTIONS, never_inline=True)


# ---------------------------------------------------------------------- options
@dataclass(frozen=True)
class ManifoldOptions:
    """How the manifold filters of one model chart, propagate and discretise the noise (codegen
    config keys ``manifold_chart``, ``manifold_side``, ``manifold_step``, ``manifold_noise``; a model
    sets its own in ``Model.codegen_defaults``).

    Attributes:
        chart: the error of a quaternion: "rotation_vector" (δθ, rad; Exp/Log) or "vector_part"
            (δp, the vector part of δq = [δp; √(1 - |δp|²)], half-angle units, |δp| < 1; paper 000
            eqs (34), (41), (52); a correction or sigma point outside |δp| < 1 is SYMKF_ERR_DOMAIN).
        side: "right": q = q̂ ⊗ δq (Hamilton; body-frame error; paper 000's δq ⊗ q̂ in its Shuster
            product (23) is this one), "left": q = δq ⊗ q̂ (Hamilton; reference-frame error).
        step: "rk4" (the model's f integrated) or "exact" (the model's ``set_discrete_step``; the
            default when the model declares one).
        noise: "continuous": Q_d = G Q Gᵀ dt, G = ∂f/∂w at the step start (or Q dt, additive);
            "held": the noises w are held over the step in the discrete step, Q_d = G_d (Q/dt) G_dᵀ
            with G_d = ∂(f_d(x̂, w) ⊟ f_d(x̂, 0))/∂w (paper 000 eqs (29), (44)); needs dt > 0.
        update: the MEKF's update of a measurement that is not a quaternion and has no noise of its
            own: "batch" (S = L Lᵀ, P - UᵀU) or "sequential" (one scalar update per component, the
            same result to round-off for a diagonal R: :func:`sequential_update`; an R with a used
            off-diagonal entry is SYMKF_ERR_ARGS).
        transition: the MEKF's error-state transition F over a step: "step" (F = ∂/∂δ through the
            discrete step f_d itself, RK4 or exact: consistent with the mean to round-off) or
            "series" (F = I + A dt + (A dt)²/2, A = ∂δ̇/∂δ the continuous error dynamics at the
            step start, derived by CasADi from the model's f through the chart; sparse: a model
            whose A has structural zeros pays only for its non-zeros; the truncation is
            |A dt|³/6 per step, e.g. 1.3e-6 for a 2 rad/s turn at 100 Hz). Needs step "rk4".
    """

    chart: str = "rotation_vector"
    side: str = "right"
    step: str = "rk4"
    noise: str = "continuous"
    update: str = "batch"
    transition: str = "step"

    CHOICES = {"chart": ("rotation_vector", "vector_part"), "side": ("right", "left"), "step": ("rk4", "exact"),
               "noise": ("continuous", "held"), "update": ("batch", "sequential"), "transition": ("step", "series")}

    @classmethod
    def for_model(cls, model: Model, config: CodegenConfig) -> "ManifoldOptions":
        defaults = cls(step="exact" if model.discrete_step is not None else "rk4")
        chosen = cls(**{k: config.get(f"manifold_{k}", getattr(defaults, k)) for k in cls.CHOICES})
        for key, allowed in cls.CHOICES.items():
            if getattr(chosen, key) not in allowed:
                raise ConfigError(f"model '{model.name}': manifold_{key} must be one of {allowed}, "
                                 f"got {getattr(chosen, key)!r}")
        if chosen.step == "exact" and model.discrete_step is None:
            raise ConfigError(f"model '{model.name}': manifold_step 'exact' needs Model.set_discrete_step()")
        if chosen.transition == "series" and chosen.step != "rk4":
            raise ConfigError(f"model '{model.name}': manifold_transition 'series' needs manifold_step 'rk4' "
                              "(the series is of the continuous f)")
        if chosen.noise == "held" and not model.noises:
            raise ConfigError(f"model '{model.name}': manifold_noise 'held' needs process noises (Model.noise())")
        return chosen


register_options(*(f"manifold_{key}" for key in ManifoldOptions.CHOICES), "manifold_run_variants")


def run_variants(model: Model, config: CodegenConfig, name: str, size: int) -> list[tuple[int, ...]]:
    """The mask patterns of measurement ``name`` (``size`` mask entries) that get their own run
    kernel (codegen option ``manifold_run_variants``: a sequence of sets of mask entries, e.g.
    ``((3,), (4, 5, 6))``; default none), largest first: :func:`mekf_run_kernels`."""
    patterns = []
    for pattern in config.get("manifold_run_variants", ()) or ():
        entries = tuple(sorted({int(i) for i in pattern}))
        if any(i < 0 or i >= size for i in entries):
            raise ConfigError(f"model '{model.name}': manifold_run_variants {pattern!r}: measurement '{name}' has "
                              f"{size} components")
        patterns.append(entries)
    return sorted(set(patterns), key=lambda e: (-len(e), e))


# ---------------------------------------------------------------------- the chart
class Chart:
    """The model's state space as a product of unit-quaternion spheres and R^k: ⊞, ⊟, projection."""

    def __init__(self, model: Model, options: ManifoldOptions = ManifoldOptions()):
        self.options = options
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

    # one quaternion: the options' error parametrisation and side
    def error_quaternion(self, delta) -> tuple[ca.SX, ca.SX]:
        """δq of a 3-vector error and a 0/1 flag that it is inside the chart's domain."""
        if self.options.chart == "vector_part":
            return quat.quaternion_from_error_vector(delta)
        return quat.rotvec_to_quaternion(delta), ca.SX(1)

    def error_vector(self, delta_q) -> ca.SX:
        """The 3-vector of an error quaternion (the shorter rotation: δq and -δq give the same)."""
        if self.options.chart == "vector_part":
            return ca.if_else(delta_q[3] < 0, -1, 1) * delta_q[0:3]
        return quat.quaternion_to_rotvec(delta_q)

    def quaternion_retract(self, q, delta) -> ca.SX:
        """q ⊞ δ: q ⊗ δq (right) or δq ⊗ q (left), Hamilton, renormalised."""
        delta_q, _ = self.error_quaternion(delta)
        moved = quat.hamilton(q, delta_q) if self.options.side == "right" else quat.hamilton(delta_q, q)
        return quat.normalize(moved)

    def quaternion_local(self, q, q_ref) -> ca.SX:
        """q ⊟ q_ref: the error vector of q_ref⁻¹ ⊗ q (right) or q ⊗ q_ref⁻¹ (left)."""
        q, q_ref = quat.normalize(q), quat.conjugate(quat.normalize(q_ref))
        return self.error_vector(quat.hamilton(q_ref, q) if self.options.side == "right" else quat.hamilton(q, q_ref))

    def retract(self, x, delta) -> ca.SX:
        """x ⊞ δ: the quaternion retraction per quaternion, x + δ for ordinary states."""
        qs = [(i, self.quaternion_retract(x[i:i + 4], delta[e:e + 3])) for i, e in self.quaternions]
        return self._assemble(self.n, qs, [(i, x[i] + delta[e]) for i, e in self.ordinary])

    def local(self, x, x_ref) -> ca.SX:
        """x ⊟ x_ref: the quaternion error vector per quaternion, x - x_ref otherwise."""
        qs = [(e, self.quaternion_local(x[i:i + 4], x_ref[i:i + 4])) for i, e in self.quaternions]
        return self._assemble(self.n_error, qs, [(e, x[i] - x_ref[i]) for i, e in self.ordinary])

    def retract_linear(self, x, delta) -> ca.SX:
        """δq ≈ [δ/c; 1] composed on the chart's side (c = 2 for rotation vectors, 1 for vector
        parts; not renormalised), x + δ otherwise: equal to x ⊞ δ to first order at δ = 0, so its
        Jacobian there is ∂(x ⊞ δ)/∂δ without the series and trigonometry of Exp."""
        scale = 0.5 if self.options.chart == "rotation_vector" else 1.0
        qs = [(i, self._compose(x[i:i + 4], ca.vertcat(scale * delta[e:e + 3], 1))) for i, e in self.quaternions]
        return self._assemble(self.n, qs, [(i, x[i] + delta[e]) for i, e in self.ordinary])

    def quaternion_local_linear(self, q, q_ref) -> ca.SX:
        """c vec(q_ref⁻¹ ⊗ q) (right) or c vec(q ⊗ q_ref⁻¹) (left) for unit q, q_ref: equal to
        q ⊟ q_ref to first order at q = q_ref (Log(q) = 2 vec(q) + O(|δθ|³)), without atan2."""
        scale = 2.0 if self.options.chart == "rotation_vector" else 1.0
        error = quat.hamilton(quat.conjugate(q_ref), q) if self.options.side == "right" else \
            quat.hamilton(q, quat.conjugate(q_ref))
        return scale * error[:3]

    def local_linear(self, x, x_ref) -> ca.SX:
        """The first-order x ⊟ x_ref: :meth:`quaternion_local_linear` per quaternion, x - x_ref otherwise."""
        qs = [(e, self.quaternion_local_linear(x[i:i + 4], x_ref[i:i + 4])) for i, e in self.quaternions]
        return self._assemble(self.n_error, qs, [(e, x[i] - x_ref[i]) for i, e in self.ordinary])

    def _compose(self, q, delta_q) -> ca.SX:
        return quat.hamilton(q, delta_q) if self.options.side == "right" else quat.hamilton(delta_q, q)

    def in_domain_all(self, deltas) -> ca.SX:
        """1 if every δ of a sigma set is inside the chart."""
        flag = ca.SX(1)
        for d in deltas:
            flag = flag * self.in_domain(d)
        return flag

    def in_domain(self, delta) -> ca.SX:
        """1 if every quaternion error of δ is inside the chart (always, for rotation vectors)."""
        flag = ca.SX(1)
        for _, e in self.quaternions:
            flag = flag * self.error_quaternion(delta[e:e + 3])[1]
        return flag

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
                                   _CALLED)
        self.local = ca.Function(f"{prefix}_local", [x, x_ref], [chart.local(x, x_ref)], ["x", "x_ref"], ["delta"],
                                 _CALLED)
        self.fd_noisy = self._noisy_step(model, fns)
        fd = (lambda *a: self.fd_noisy(*a, ca.DM.zeros(len(model.noises)))) if self.options.step == "exact" \
            else fns.fd_inline
        step = chart.project(fd(t, dt, x, u, p))
        self.step = ca.Function(f"{prefix}_manifold_fd", [t, dt, x, u, p], [step],
                                ["t", "dt", "x", "u", "p"], ["x"], _CALLED)
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
                           ["t", "dt", "x", "u", "p", "w"], ["x"], _CALLED)

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
                                             [noisy(t, x, u, p, q, v)], ["t", "x", "u", "p", "q", "v"], ["z"], _CALLED)
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


# ---------------------------------------------------------------------- MEKF
def mekf_update_expr(mf: ManifoldFunctions, ms: ManifoldSymbols, name: str, msym: dict, wrap, state=None,
                     trusted: bool = False):
    """The MEKF update of x̂, P at t (the kernel's inputs), or of ``state`` = (t, x, P) of a fused
    step: a predicted P, exactly symmetric, whose PSD and finiteness need no check of their own
    (checked in the step's input; a result that overflows is refused by the backends' output
    checks; if the prediction failed, the step's outputs are its inputs and y, S are not read).
    Batch or sequential (:class:`ManifoldOptions`); ``trusted``: R's diagonal is not tested (a run's
    trusted kernel, :func:`mekf_run_kernels`)."""
    s = ms.base.sym
    t, x, P = state or (s["t"], s["x"], ms.sym["P"])
    m = measurement_input(mf.model, ms, name, msym)
    z_pred = mf.h_inline[name](t, x, s["u"], s["p"], msym["q"])
    folded = {i for pattern in run_variants(mf.model, mf.fns.config, name, msym["mask"].numel()) for i in pattern}
    H = masked_rows(m.mask, mf.jac_h[name](t, x, s["u"], s["p"], msym["q"]), folded)
    y = chart_innovation(mf, name, m, z_pred, wrap)
    HPH = linalg.sandwich(H, P)                      # sparse H: structural zeros cost nothing
    if _sequential(mf, name):
        # R must be diagonal (else SYMKF_ERR_ARGS, outputs not written): its masked diagonal only
        r = [msym["R"][i, i] * m.mask[i] * m.mask[i] + (1 - m.mask[i]) for i in range(H.shape[0])]
        S = linalg.symmetric(len(r), lambda i, j: HPH[i, j] + (r[i] if i == j else 0))
        correction, P_new, nis, ok = sequential_update(H, P, y, r, symmetric=state is not None)
        m.valid = 1 if trusted else diagonal_flag(msym["R"])
    else:
        R = masked_noise(mf.measurement_noise(name, msym["R"], t, x, s["u"], s["p"], msym["q"]), m.mask)
        S = linalg.symmetric(R.shape[0], lambda i, j: HPH[i, j] + linalg.symmetric_part(R, i, j))
        correction, P_new, nis, ok = batch_update(H, P, y, S)
    ok = ok if state is not None else ok * linalg.psd_flag(P)
    x_new = mf.retract(x, correction)               # multiplicative reset
    return (x_new, P_new, y, S, ok, nis, m.finite, mf.chart.in_domain(correction)), m


def masked_rows(mask, J, guarded=()) -> ca.SX:
    """diag(mask) J, the rows in ``guarded`` exactly 0 when masked even where J is not finite (e.g.
    the heading's H with no horizontal field: 0 * Inf): their entries are clamped to ±BIG first
    (NaN -> -BIG; fmin/fmax, which CasADi does not push into later products as it does an
    if_else). The guarded rows are those a kernel variant folds away (``manifold_run_variants``),
    so that the general kernel (VM backend, a run's first or gated steps) ignores a masked row as
    the variant does; a used row with a non-finite entry stays refused. Sparse."""
    H = ca.SX(J)
    rows, cols = J.sparsity().get_triplet()
    for i, j in zip(rows, cols):
        H[i, j] = mask[i] * (ca.fmin(ca.fmax(J[i, j], -BIG), BIG) if i in guarded else J[i, j])
    return H


#: The clamp of :func:`masked_rows` (finite, and far above any derivative a filter can use).
BIG = 1e300


def _sequential(mf: ManifoldFunctions, name: str) -> bool:
    meas = mf.model.measurements[name]
    return mf.options.update == "sequential" and not meas.quaternion and name not in mf.noise_jac


def batch_update(H, P, y, S):
    """With S = L Lᵀ and U = L⁻¹ H P: δ̂ = K y = Uᵀ L⁻¹ y and P⁺ = P - K S Kᵀ = P - Uᵀ U (lower
    triangle, mirrored), as the Kalman EKF and UKF. Returns δ̂, P⁺, yᵀ S⁻¹ y and the Cholesky flag."""
    L, ok = linalg.cholesky(S)
    U = linalg.solve_lower(L, H @ P)
    white = linalg.solve_lower(L, y)
    UtU = linalg.gram(U)
    P_new = linalg.symmetric(P.shape[0], lambda i, j: linalg.symmetric_part(P, i, j) - UtU[i, j])
    return U.T @ white, P_new, ca.sumsqr(white), ok


def sequential_update(H, P, y, r, symmetric: bool = False):
    """The same update as :func:`batch_update` for a diagonal R, as m scalar updates in turn
    (Maybeck, "Stochastic Models, Estimation and Control" Vol. 1, 1979, sec. 7.7; exact in exact
    arithmetic, both linearised at the prior): per component i, with the correction δ so far,
    s_i = hᵢ P hᵢᵀ + R_ii, k = P hᵢᵀ / s_i, δ += k (y_i - hᵢ δ), P -= k (P hᵢᵀ)ᵀ (lower triangle).
    The s_i are the pivots of S = H P Hᵀ + R (its LDLᵀ), so all s_i > 0 is the batch's Cholesky
    flag, and Σ (y_i - hᵢ δ)² / s_i = yᵀ S⁻¹ y. A masked row (hᵢ = 0, y_i = 0, r_i = 1) changes nothing.
    ``r``: the diagonal of R; ``symmetric``: P is exactly symmetric (else its symmetric part is used)."""
    n = P.shape[0]
    P = P if symmetric else linalg.symmetric(n, lambda i, j: linalg.symmetric_part(P, i, j))
    delta, nis, ok = ca.SX.zeros(n), ca.SX(0), ca.SX(1)
    for i in range(H.shape[0]):
        h = H[i, :]
        Ph = P @ h.T
        s = ca.dot(h.T, Ph) + r[i]
        usable = (s > 0) * (s < ca.inf)
        ok = ok * usable
        inverse = 1 / linalg.guarded(s, usable)
        residual = y[i] - ca.dot(h.T, delta)
        gain = Ph * inverse
        delta = delta + gain * residual
        nis = nis + residual * residual * inverse
        P = linalg.symmetric(n, lambda a, b, P=P, gain=gain, Ph=Ph: P[a, b] - gain[a] * Ph[b])
    return delta, P, nis, ok


def diagonal_flag(R) -> ca.SX:
    """1 if the symmetric part of R (the one a batch update uses) is diagonal, else 0: a sequential
    update needs uncorrelated components."""
    flag = ca.SX(1)
    for i in range(R.shape[0]):
        for j in range(i):
            flag = flag * (R[i, j] + R[j, i] == 0)
    return flag


def mekf_kernels(model: Model, symbols: Symbols, fns: ModelFunctions) -> Family:
    _require_quaternion(model, "mekf")
    mf, ms = ManifoldFunctions(model, fns), ManifoldSymbols(model, symbols)
    s, P = symbols.sym, ms.sym["P"]
    x_pred, P_pred = mekf_predict_expr(model, mf, ms)
    doc = _predict_doc(model, "Multiplicative EKF", f"{_step_words(mf)} then |q| = 1; P = F P F^T + Q_d, "
                       "F = d(f_d(x (+) d) (-) f_d(x))/dd in error coordinates")
    predict = predict_kernel("mekf_predict", doc, ms, mf, x_pred, P_pred, linalg.psd_flag(P), PREDICT_INPUTS)
    kernels = [predict]
    for name, meas in model.measurements.items():
        msym, marg = ms.measurement(name)
        upd, m = mekf_update_expr(mf, ms, name, msym, meas.wrap)
        update = make_kernel(
            f"mekf_update_{name}", f"Multiplicative EKF update with '{name}': H = dh(x (+) d)/dd, P - K S K^T, "
            "reset x = x (+) K y (masked, gated).", symbols, msym, marg, UPDATE_INPUTS,
            update_outputs(mf.chart, upd, s["x"], P, msym, m))
        step = mekf_step_kernel(model, mf, ms, name, predict, update, (x_pred, P_pred))
        run = mekf_run_kernels(model, mf, ms, name, predict, update, step, (x_pred, P_pred))
        step, step_variants = with_variants(model, mf, name, step, step.name)
        kernels += [update, step, *run, *step_variants]
    run = {name: f"mekf_run_{name}" for name in model.measurements}
    return Family(kernels, [filter_spec("mekf", "manifold_ekf", kernels, model.measurements, run=run)])


def mekf_run_kernels(model: Model, mf: ManifoldFunctions, ms: ManifoldSymbols, name: str, predict: Kernel,
                     update: Kernel, step: Kernel, predicted) -> list[Kernel]:
    """``mekf_run_<m>`` (:func:`run_kernel`) and its trusted partner ``mekf_run_<m>_trusted``, the
    kernel the C run loop iterates once a step has succeeded (``Kernel.trusted``): the carried
    x, P are then the filter's own output and R passed the step's test, so it leaves out

    - |q| = 1 of the input x: a step's x is renormalised (q / |q|, finite: checked on output);
    - R diagonal (sequential update): R is fixed along a run, and a step that succeeded had it so;
    - the PSD test of the input P (:func:`linalg.psd_flag`, 0.23k of the kernel's 2.1k operations
      for n_e = 6): P is F P Fᵀ + Q_d of a P that passed it, then scalar updates with positive
      pivots, PSD in exact arithmetic; its round-off (~1e-16 relative) is far inside the test's
      tolerance (:data:`linalg.PSD_TOLERANCE` = 1e-9 on the correlation matrix). This is the one
      check a run does not repeat that step-by-step calls do: only a P that fails the test after
      a successful step (none seen) would be coded differently (the step: NOT_PD, the run: the
      update's own code).

    The same expressions otherwise: x, P and codes bit-identical to the checked kernel's.

    With the codegen option ``manifold_run_variants`` (:func:`run_variants`), the trusted kernel
    also comes in one variant per listed mask pattern, ``mekf_run_<m>_masked_<i>_<j>...`` (the
    empty pattern: ``mekf_run_<m>_ungated``): the gate and the listed mask entries replaced by the
    constant 0, so CasADi removes what they multiply away: the masked components' scalar updates,
    their h and H rows (the heading's atan2), the gate's test and selects. The loop calls one when
    the run's gate is off (all 0) and the step's listed mask entries are exactly 0 (``Kernel.variants``).
    A masked component's scalar update changes nothing (hᵢ = 0: P - 0, δ + 0, NIS + 0; the gain's
    pivot is 1), so a variant gives the trusted kernel's x, P and codes (up to the sign of a zero)."""
    run = run_kernel(step)
    unchecked = mekf_step_kernel(model, mf, ms, name, predict, update, predicted, trusted=True)
    trusted, variants = with_variants(model, mf, name, run_kernel(unchecked, f"{run.name}_trusted", carried=()),
                                      run.name)
    return [replace(run, trusted=trusted.name), trusted, *variants]


def with_variants(model: Model, mf: ManifoldFunctions, name: str, kernel: Kernel, base: str):
    """``kernel`` with its ``variants`` (``Kernel.variants``: one per pattern of
    ``manifold_run_variants``, :func:`masked_variant`) and those variant kernels."""
    patterns = run_variants(model, mf.fns.config, name, kernel.inputs[kernel.input_index("mask")].size)
    variants = [masked_variant(kernel, base, entries) for entries in patterns]
    gate = tuple(range(kernel.inputs[kernel.input_index("gate")].size))
    conditions = tuple((v.name, (("gate", gate), ("mask", entries))) for v, entries in zip(variants, patterns))
    return replace(kernel, variants=conditions), variants


def masked_variant(kernel: Kernel, base: str, entries: tuple[int, ...]) -> Kernel:
    """``kernel`` with the gate and the mask entries ``entries`` set to the constant 0: named
    ``<base>_masked_<i>_<j>...`` (``<base>_ungated`` for no entry)."""
    f = kernel.function
    inputs = f.sx_in()
    gate, mask = inputs[kernel.input_index("gate")], inputs[kernel.input_index("mask")]
    fixed = [gate[i] for i in range(gate.numel())] + [mask[i] for i in entries]
    outputs = ca.substitute(f.call(inputs), [ca.vertcat(*fixed)], [ca.DM.zeros(len(fixed))])
    name = f"{base}_masked_{'_'.join(map(str, entries))}" if entries else f"{base}_ungated"
    function = ca.Function(f"{f.name().split('_k_')[0]}_k_{name}", inputs, outputs, f.name_in(), f.name_out(),
                           FUNCTION_OPTIONS)
    what = f"mask entries {list(entries)} and the gate 0" if entries else "the gate 0 (off)"
    return Kernel(name, function, f"{kernel.doc} Specialised for {what}: called for it by the wrapper "
                  f"of {kernel.name} and by the run loop.", kernel.inputs, kernel.outputs, (), kernel.per_step)


def run_kernel(step: Kernel, name: str = "", carried=None) -> Kernel:
    """``mekf_run_<measurement>``: the fused step without its diagnostics y and S, the kernel the C
    run loop iterates (``FilterSpec.run``): a run keeps only x, P and the status of each step, so
    CasADi drops what only y and S need (the S matrix: ~0.25k of the MARG step's ~2.3k operations)
    and the loop neither checks nor copies them. x, P and the status are the step's own expressions:
    the same numbers and codes, except that the step wrapper also refuses a step whose y or S
    output is not finite (SYMKF_ERR_NONFINITE) and the run does not look at them."""
    f = step.function
    keep = [i for i in range(f.n_out()) if f.name_out(i) in (*step.carried, "status")]
    name = name or step.name.replace("mekf_step_", "mekf_run_")
    function = ca.Function(f"{f.name().split('_k_mekf_step_')[0]}_k_{name}", f.sx_in(),
                           [f.call(f.sx_in())[i] for i in keep], f.name_in(), [f.name_out(i) for i in keep],
                           FUNCTION_OPTIONS)
    what = "the step the run loop iterates" if carried is None else \
        "the step the run loop iterates once a step has succeeded (no test of |q|, P PSD or R diagonal)"
    return Kernel(name, function, f"{step.doc} Without the diagnostics y, S: {what}.", step.inputs,
                  tuple(step.outputs[i] for i in keep), step.carried if carried is None else tuple(carried),
                  step.per_step)


PREDICT_INPUTS = ["t", "dt", "x", "P", "u", "p", "Q"]


def mekf_predict_expr(model: Model, mf: ManifoldFunctions, ms: ManifoldSymbols):
    """x̂⁻ = f_d(x̂) projected, P⁻ = F P Fᵀ + Q_d (lower triangle, mirrored)."""
    s, P, Q = ms.base.sym, ms.sym["P"], ms.sym["Q"]
    x_pred, F = mf.step_and_jac(s["t"], s["dt"], s["x"], s["u"], s["p"])
    FPF, Qd = linalg.sandwich(F, P), error_process_noise(model, mf, ms.base, Q, s["x"], s["t"], s["dt"])
    return x_pred, linalg.symmetric(P.shape[0], lambda i, j: FPF[i, j] + linalg.symmetric_part(Qd, i, j))


def mekf_step_kernel(model: Model, mf: ManifoldFunctions, ms: ManifoldSymbols, name: str, predict: Kernel,
                     update: Kernel, predicted, trusted: bool = False) -> Kernel:
    """Predict then update at t + dt as ONE expression (same results and codes as
    ``kernels.compose_step`` of the two kernels): the inputs are checked once (|q| = 1, P PSD; their
    finiteness by the callers), the predicted P needs no PSD check of its own (F P Fᵀ + Q_d of a PSD
    P), the update works on the predicted x, P directly, and x, P are selected only by the gate (a
    failed step's outputs are not written: :func:`update_outputs`). ``trusted``: without the tests
    of |q| = 1, P PSD and R diagonal (:func:`mekf_run_kernels`)."""
    s, P = ms.base.sym, ms.sym["P"]
    msym, marg = ms.measurement(name)
    status_pred = predict_status(mf, ms.base, 1 if trusted else linalg.psd_flag(P), unit=not trusted)
    x1, P1 = predicted          # if the prediction failed, the outputs below are the inputs
    upd, m = mekf_update_expr(mf, ms, name, msym, model.measurements[name].wrap, state=(s["t"] + s["dt"], x1, P1),
                              trusted=trusted)
    outputs = dict(update_outputs(mf.chart, upd, x1, P1, msym, m))
    failed = status_pred != 0
    outputs["status"] = linalg.select(failed, status_pred, outputs["status"])   # x, P: not written then
    inputs = sorted(set(PREDICT_INPUTS) | set(UPDATE_INPUTS), key=CANONICAL_ORDER.index)
    doc = (f"{predict.doc.split(' (')[0]}; then {update.doc.replace(' at time t ', ' at t + dt ')} "
           "Both in one call.")
    return make_kernel(f"mekf_step_{name}", doc, ms.base, msym, marg, inputs, list(outputs.items()),
                       carried=("x", "P"), per_step=tuple(i for i in inputs if i in ("t", "dt", "u", "q", "z", "mask")))


def _step_words(mf: ManifoldFunctions) -> str:
    return "the model's exact step" if mf.options.step == "exact" else "RK4"


# ---------------------------------------------------------------------- manifold UKF
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
    _require_quaternion(model, "mukf")
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


def _require_quaternion(model: Model, family: str) -> None:
    if not model.quaternions:
        raise ValueError(f"filter family '{family}' is for models with quaternion_state(); model '{model.name}' "
                         "has none (use 'ekf' / 'ukf')")


register_family("mekf", mekf_kernels)
register_family("mukf", mukf_kernels)

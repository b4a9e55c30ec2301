"""The manifold filters' chart: the state space of a model with unit-quaternion states, its
options (:class:`ManifoldOptions`), and the eigenvector quaternion mean.

A model declares its quaternions with ``Model.quaternion_state`` (scalar-last, unit norm) beside
ordinary states; the families "mekf", "mukf" (``mekf.py``, ``mukf.py``) and "sukf", "aukf"
(``quaternion_filters.py``) work on this chart.

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

**Options** (:class:`ManifoldOptions`, codegen config
``manifold_chart/_side/_step/_noise/_update/_transition``, a model's own in ``Model.codegen_defaults``):
the error may instead be the vector part δp of δq = [δp; √(1 - |δp|²)] (paper 000 eqs (34), (41),
(52); half-angle units; |δp| >= 1 is SYMKF_ERR_DOMAIN), on the left (δq ⊗ q̂, reference frame)
instead of the right; the step may be the model's exact one (``Model.set_discrete_step``) instead
of RK4; the process noise may be *held* over the step inside that step (Q_d = G_d (Q/dt) G_dᵀ, paper 000 eq (29)).
``models/attitude.py`` sets paper 000's options.

Quaternion mean without LAPACK (Markley et al., "Averaging quaternions", JGCD 30(4) 2007; paper
000 eqs (36)-(38)): N = Σ W_i Ψ(q_i)Ψ(q_i)ᵀ = (Σ W_i) I - M for unit q_i with M = Σ W_i q_i q_iᵀ,
so the wanted eigenvector is M's for its largest eigenvalue. M is shifted by the total negative
weight (to make it positive semidefinite) and squared ``MEAN_SQUARINGS`` times with trace
normalisation (A ← A²/tr A², i.e. M^(2^k): the other eigen-directions shrink as
(λ_j/λ_1)^(2^k)); the column with the largest diagonal is then polished by ``MEAN_POLISH`` power
steps and its sign aligned with a reference quaternion. Fixed work, branch-free, no LAPACK.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import casadi as ca

from symkf.models import quaternion as quat
from symkf.models.base import Model
from .. import linalg
from ..spec import CodegenConfig, ConfigError, option

#: An input state whose quaternion norm differs from 1 by more than this is SYMKF_ERR_DOMAIN.
QUATERNION_NORM_TOLERANCE = 1e-6
#: Squarings of the shifted M in the quaternion mean: off-dominant directions shrink as r^(2^k).
MEAN_SQUARINGS = 32
#: Power-iteration steps that polish the eigenvector after the squarings.
MEAN_POLISH = 2


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
            same result to round-off for a diagonal R: :func:`~symkf.codegen.families.mekf.sequential_update`; an R with a used
            off-diagonal entry is SYMKF_ERR_ARGS).
        transition: the MEKF's error-state transition F over a step: "step" (F = ∂/∂δ through the
            discrete step f_d itself, RK4 or exact: consistent with the mean to round-off) or
            "series" (F = I + A dt + (A dt)²/2, A = ∂δ̇/∂δ the continuous error dynamics at the
            step start, derived by CasADi from the model's f through the chart; sparse: a model
            whose A has structural zeros pays only for its non-zeros; the truncation is
            |A dt|³/6 per step, e.g. 1.3e-6 for a 2 rad/s turn at 100 Hz). Needs step "rk4".
    """

    chart: str = option("rotation_vector", "a quaternion's error: 'rotation_vector' (rad) or 'vector_part' "
                                           "(half-angle units, paper 000)")
    side: str = option("right", "the error's side: 'right' q = q̂ ⊗ δq (body frame) or 'left' q = δq ⊗ q̂")
    step: str = option("rk4", "the step: 'rk4' (the model's f) or 'exact' (Model.set_discrete_step; its default "
                              "when the model declares one)")
    noise: str = option("continuous", "process noise: 'continuous' (Q_d = G Q Gᵀ dt) or 'held' over the step "
                                      "(paper 000 eq (29))")
    update: str = option("batch", "the MEKF update: 'batch' or 'sequential' (one scalar update per component, "
                                  "diagonal R)")
    transition: str = option("step", "the MEKF's F: 'step' (through f_d) or 'series' (I + A dt + (A dt)²/2)")

    prefix: ClassVar[str] = "manifold_"

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



# ---------------------------------------------------------------------- quaternion mean
def quaternion_mean(quaternions: ca.SX, weights: ca.SX, q_ref: ca.SX,
                    squarings: int = MEAN_SQUARINGS, polish: int = MEAN_POLISH) -> ca.SX:
    """Eqs (36)-(38): the unit eigenvector of N for its smallest eigenvalue, sign aligned with q_ref."""
    n = quaternions.shape[1]
    M = sum((weights[i] * quaternions[:, i] @ quaternions[:, i].T for i in range(n)), ca.SX.zeros(4, 4))
    shift = sum((ca.fmax(-weights[i], 0) for i in range(n)), ca.SX(0))
    shifted = M + shift * ca.SX.eye(4)
    A = shifted / ca.fmax(ca.trace(shifted), linalg.TINY)
    for _ in range(squarings):
        A = A @ A
        A = A / ca.fmax(ca.trace(A), linalg.TINY)
    column, best = A[:, 0], A[0, 0]
    for j in range(1, 4):
        larger = A[j, j] > best
        column, best = ca.if_else(larger, A[:, j], column), ca.fmax(A[j, j], best)
    v = column / ca.norm_2(column)
    for _ in range(polish):
        v = shifted @ v
        v = v / ca.norm_2(v)
    return ca.if_else(ca.dot(v, q_ref) < 0, -1, 1) * v

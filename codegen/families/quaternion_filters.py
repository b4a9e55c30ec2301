"""Quaternion attitude filters of paper 000 (Leeghim et al. 2008) as generated kernels.

Family ``"attitude"`` (for ``models/attitude.py``). State x = [q (4); b (3)]; covariance P (6x6)
of the error state δx = [δp; δb], δp the vector part of the error quaternion δq = q ⊗ q̂⁻¹
(eq (34); half-angle units, so P0 = 0.01 I6 of section V means ~0.1 rad half-angle, |δp| < 1).
Q is the 6x6 PSD of w = [η_a; η_b] (eq (29)); the discrete noise covariance is Q/Δt (η held
over the step, see models/attitude.py). R is the 3x3 covariance of the star-tracker noise
rotation vector η_s (eq (31)).

Kernels (the C names are ``attitude_<kernel>``):

- ``mekf_predict / mekf_update_star_tracker / mekf_step_star_tracker``: the multiplicative EKF,
  the paper's "Kalman filter" baseline (Lefferts, Markley, Shuster). F = ∂δx⁺/∂δx,
  G = ∂δx⁺/∂w, H = ∂δp_s/∂δx, D = ∂δp_s/∂η_s are derived by CasADi from the model's propagation
  (44)-(45) and star tracker (30); multiplicative reset (52); Joseph-form covariance update.
- ``ukf_predict / ukf_update_star_tracker / ukf_step_star_tracker``: the paper's efficient UKF.
  Propagation in the space [x, w] (eqs (9)-(15), (39)-(45)): 2·12+1 = 25 sigma points from
  blockdiag(√P, √(Q/Δt)) (two small Cholesky factors, eq (9)), γ_p = √(12+κ), weights
  κ/(12+κ) and 1/(2(12+κ)) (eq (12) prints κ in the numerator of the outer weights, a typo: the
  weights must sum to 1). Quaternion sigma points δq ⊗ q̂ from (41)-(42); the quaternion mean
  is the eigenvector of N (36) for its smallest eigenvalue (38). Update in the space [x, v]
  (eqs (16)-(22), (46)-(53)): 2·9+1 = 19 points, γ_m = √(9+κ), mean predicted star-tracker
  quaternion again by (38), innovation (50), gain (5), reset (51)-(52), covariance (7).
- ``aukf_predict / aukf_step_star_tracker``: the same UKF in the full augmented space [x, w, v]
  (15 dims, 31 points, one 15x15 Cholesky factor per step; the update reuses the propagated
  sigma set), for the paper's efficiency comparison.

Kernels are branch-free: a step kernel with mask = 0 still evaluates its update and discards it,
so a filter object calls the predict kernel for gyro-only steps; the C run loop uses the step.
- ``quaternion_mean_<n>``: the eigenvector mean alone, for tests.

Quaternion mean without LAPACK: N = Σ W_i Ψ(q_i)Ψ(q_i)ᵀ = (Σ W_i) I - M for unit q_i with
M = Σ W_i q_i q_iᵀ, so the wanted eigenvector is M's for its largest eigenvalue. M is shifted by
the total negative weight (to make it positive semidefinite) and squared ``MEAN_SQUARINGS``
times with trace normalisation (A ← A²/tr A², i.e. M^(2^k): the other eigen-directions shrink as
(λ_j/λ_1)^(2^k)); the column with the largest diagonal is then polished by ``MEAN_POLISH`` power
steps and its sign aligned with a reference quaternion. Fixed work, branch-free, no LAPACK.

Readings of the paper (where the printed text is ambiguous or mistyped):

- Eq (12) prints κ/(2(2n+κ)) for the outer weights; 1/(2(2n+κ)) is used (weights sum to 1).
- Eq (34) prints δp_i = -Ψᵀ(q_i) q; with the product (23) the vector part of q_i ⊗ q⁻¹ is
  -Ξᵀ(q_i) q (tested). For the scalar weights used here N (36) is the same either way,
  since Ψ Ψᵀ = Ξ Ξᵀ = I - q qᵀ.
- Eq (48) spreads the star-tracker noise as an error-quaternion vector part. Here η_s is a
  rotation vector (Table 1's σ_s read as angles per axis) and the noise sigma points go through
  the model's star tracker (30) itself, which is exact and has no |δp| < 1 limit.
- κ is not given: the default κ = 1 keeps every weight positive (κ = 3 - n would make W_0 < 0).

Failures are status codes: a sigma vector or a correction with |δp| >= 1 (eq (41)/(52)) or
n + κ <= 0 gives SYMKF_ERR_DOMAIN; a non-positive-definite P, Q, R or innovation covariance
gives SYMKF_ERR_NOT_PD; a star-tracker quaternion whose norm is off 1 by more than
``MEASUREMENT_NORM_TOLERANCE`` is SYMKF_ERR_DOMAIN (within it, it is normalised); a non-finite
one is SYMKF_ERR_NONFINITE. A masked update (mask = 0) returns x and P unchanged.
"""
from __future__ import annotations

import casadi as ca

from symkf.models import attitude as att
from symkf.models import quaternion as quat
from .. import linalg
from ..discretize import FUNCTION_OPTIONS
from ..kernels import Symbols, compose_step, filter_spec, make_kernel, register_family
from ..spec import STATUS_DOMAIN, STATUS_NONFINITE, STATUS_NOT_PD, Arg, Family, Kernel

#: UKF scaling κ used unless given: keeps every weight positive (paper 000 leaves κ open).
DEFAULT_KAPPA = 1.0
#: Squarings of the shifted M in the quaternion mean: off-dominant directions shrink as r^(2^k).
MEAN_SQUARINGS = 32
#: Power-iteration steps that polish the eigenvector after the squarings.
MEAN_POLISH = 2
#: A star-tracker quaternion is normalised if | |z| - 1 | <= this, rejected (SYMKF_ERR_DOMAIN) otherwise.
MEASUREMENT_NORM_TOLERANCE = 1e-3
#: Dimensions: error state, process noise w = [η_a; η_b], star-tracker noise η_s.
N_ERROR, N_PROCESS_NOISE, N_MEAS_NOISE = 6, 6, 3
#: Sigma-point counts of the three filters (for the bench and the docs).
N_PROPAGATION_POINTS = 2 * (N_ERROR + N_PROCESS_NOISE) + 1     # [x, w]: 25
N_UPDATE_POINTS = 2 * (N_ERROR + N_MEAS_NOISE) + 1             # [x, v]: 19
N_AUGMENTED_POINTS = 2 * (N_ERROR + N_PROCESS_NOISE + N_MEAS_NOISE) + 1   # [x, w, v]: 31

_OPTIONS = dict(FUNCTION_OPTIONS, never_inline=True)


# ---------------------------------------------------------------------- shared CasADi functions
class AttitudeFunctions:
    """The model's equations and the quaternion helpers as never_inline CasADi Functions.

    Each is generated once in C and called per sigma point. The NumPy reference
    (runtime/attitude.py) evaluates the very same Functions.
    """

    def __init__(self, prefix: str = "attitude"):
        q, q_ref, b = ca.SX.sym("q", 4), ca.SX.sym("q_ref", 4), ca.SX.sym("b", 3)
        omega_g, eta_a, eta_b = ca.SX.sym("omega_g", 3), ca.SX.sym("eta_a", 3), ca.SX.sym("eta_b", 3)
        eta_s, dt, delta_x = ca.SX.sym("eta_s", 3), ca.SX.sym("dt"), ca.SX.sym("delta_x", N_ERROR)
        q_next, b_next = att.propagate(q, b, omega_g, eta_a, eta_b, dt)
        self.propagate = ca.Function(f"{prefix}_propagate", [q, b, omega_g, eta_a, eta_b, dt], [q_next, b_next],
                                     ["q", "b", "omega_g", "eta_a", "eta_b", "dt"], ["q", "b"], _OPTIONS)
        self.star_tracker = ca.Function(f"{prefix}_star_tracker", [q, eta_s], [att.star_tracker(q, eta_s)],
                                        ["q", "eta_s"], ["q_s"], _OPTIONS)
        self.error_vector = ca.Function(f"{prefix}_error_vector", [q, q_ref], [error_vector(q, q_ref)],
                                        ["q", "q_ref"], ["delta_p"], _OPTIONS)
        q_sigma, b_sigma, ok = perturbed_state(delta_x, q, b)
        self.perturb = ca.Function(f"{prefix}_perturb", [delta_x, q, b], [q_sigma, b_sigma, ok],
                                   ["delta_x", "q", "b"], ["q", "b", "ok"], _OPTIONS)
        self.psi = ca.Function(f"{prefix}_psi", [q], [quat.psi_matrix(q)], ["q"], ["Psi"], FUNCTION_OPTIONS)
        self._means: dict[int, ca.Function] = {}
        self.prefix = prefix

    def mean(self, n_points: int) -> ca.Function:
        """The eigenvector quaternion mean (36)-(38) of n_points quaternions (cached per size)."""
        if n_points not in self._means:
            quaternions, weights, q_ref = ca.SX.sym("quaternions", 4, n_points), ca.SX.sym("weights", n_points), \
                ca.SX.sym("q_ref", 4)
            self._means[n_points] = ca.Function(
                f"{self.prefix}_quaternion_mean_{n_points}", [quaternions, weights, q_ref],
                [quaternion_mean(quaternions, weights, q_ref)], ["quaternions", "weights", "q_ref"], ["q"], _OPTIONS)
        return self._means[n_points]


def error_vector(q, q_ref) -> ca.SX:
    """δp of δq = q ⊗ q_ref⁻¹ (eq (34)), sign chosen so that δq4 >= 0 (the shorter rotation)."""
    delta_q = quat.error_quaternion(q, q_ref)
    return ca.if_else(delta_q[3] < 0, -1, 1) * delta_q[0:3]


def perturbed_state(delta_x, q_hat, b_hat):
    """Eqs (41)-(42): q = δq(δp) ⊗ q̂, b = b̂ + δb; plus the 0/1 flag |δp| < 1."""
    delta_q, ok = quat.quaternion_from_error_vector(delta_x[0:3])
    return quat.otimes(delta_q, q_hat), b_hat + delta_x[3:6], ok


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


def _symmetric_sum(weights, left, right) -> ca.SX:
    return sum((w * a @ b.T for w, a, b in zip(weights, left, right)), ca.SX.zeros(left[0].shape[0], right[0].shape[0]))


def _all(flags) -> ca.SX:
    result = ca.SX(1)
    for flag in flags:
        result = result * flag
    return result


def _status(checks: list[tuple[ca.SX, int]]) -> ca.SX:
    """The code of the first failed check (in order), or 0."""
    status = ca.SX(0)
    for ok, code in reversed(checks):
        status = linalg.select(ok, status, code)
    return status


def _ukf_weights(dimension: int, kappa: ca.SX) -> list:
    scale = linalg.guarded(dimension + kappa, dimension + kappa > 0)   # else refused: SYMKF_ERR_DOMAIN
    return [kappa / scale] + [0.5 / scale] * (2 * dimension)


def _sigma_offsets(factor: ca.SX, gamma: ca.SX) -> list[ca.SX]:
    """[0, +γ L_i..., -γ L_i...] (eqs (12)-(13), (18)-(19))."""
    n = factor.shape[1]
    columns = [gamma * factor[:, i] for i in range(n)]
    return [ca.SX.zeros(factor.shape[0], 1)] + columns + [-c for c in columns]


def _block_diagonal_factor(*matrices) -> tuple[ca.SX, ca.SX]:
    """Eq (9): √blockdiag(A, B, ...) = blockdiag(√A, √B, ...) with a 0/1 all-PD flag."""
    factors, flags = zip(*[linalg.cholesky(m) for m in matrices])
    return ca.diagcat(*factors), _all(flags)


# ---------------------------------------------------------------------- symbols
class AttitudeSymbols:
    """Kernel arguments whose shapes differ from the generic ones (6x6 P and Q, 4-vector z)."""

    def __init__(self, symbols: Symbols):
        self.base = symbols
        self.sym = {"P": ca.SX.sym("P", N_ERROR, N_ERROR), "Q": ca.SX.sym("Q", N_PROCESS_NOISE, N_PROCESS_NOISE),
                    "z": ca.SX.sym("z", 4), "mask": ca.SX.sym("mask"), "R": ca.SX.sym("R", N_MEAS_NOISE, N_MEAS_NOISE)}
        self.arg = {
            "P": Arg("P", (N_ERROR, N_ERROR), "-, rad/s", "covariance of the error state [δp (half-angle); δb]"),
            "Q": Arg("Q", (N_PROCESS_NOISE, N_PROCESS_NOISE), "rad²/s, rad²/s³",
                     "PSD of w = [η_a; η_b] (eq 29); discrete covariance Q/dt"),
            "u": Arg("u", (3, 1), "rad/s", "gyro output ω_g (eq 28)"),
            "z": Arg("z", (4, 1), "-", "star-tracker quaternion q_s, scalar-last (eq 30)"),
            "mask": Arg("mask", (1, 1), "-", "1: use the star tracker, 0: no measurement (x, P unchanged)"),
            "R": Arg("R", (N_MEAS_NOISE, N_MEAS_NOISE), "rad²", "covariance of the star-tracker noise η_s (eq 31)"),
            "y": Arg("y", (3, 1), "-", "innovation δp_s of q_s ⊗ q̂_s⁻¹ (eq 50), 0 when masked"),
            "S": Arg("S", (3, 3), "-", "innovation covariance P^yy (eq 22)"),
        }

    def kernel(self, name: str, doc: str, inputs: list[str], outputs: list[tuple[str, ca.SX]]) -> Kernel:
        return make_kernel(name, doc, self.base, self.sym, self.arg, inputs, outputs)

    def split_state(self):
        x = self.base.sym["x"]
        return x[0:4], x[4:7]


PREDICT_INPUTS = ["t", "dt", "x", "P", "u", "Q", "kappa"]
UPDATE_INPUTS = ["t", "x", "P", "u", "z", "mask", "R", "kappa"]
MEKF_PREDICT_INPUTS = [name for name in PREDICT_INPUTS if name != "kappa"]
MEKF_UPDATE_INPUTS = [name for name in UPDATE_INPUTS if name != "kappa"]


def _measurement_checks(z: ca.SX) -> tuple[ca.SX, ca.SX, ca.SX]:
    """(normalised z, finite flag, unit-norm flag) for the bad-input rule of the module docstring."""
    finite = _all([(z[i] == z[i]) * (ca.fabs(z[i]) < ca.inf) for i in range(4)])
    norm = ca.norm_2(z)
    return z / ca.fmax(norm, linalg.TINY), finite, ca.fabs(norm - 1) <= MEASUREMENT_NORM_TOLERANCE


def _apply_correction(correction: ca.SX, q_hat: ca.SX, b_hat: ca.SX):
    """Eqs (51)-(52): q⁺ = δq̂ ⊗ q̂⁻ (renormalised against round-off drift), b⁺ = b̂⁻ + δb̂."""
    q_new, b_new, ok = perturbed_state(correction, q_hat, b_hat)
    return ca.vertcat(quat.normalize(q_new), b_new), ok


def _masked_update_outputs(s: dict, a: dict, x_new, P_new, innovation, S, checks):
    """Outputs of an update: unchanged x, P when masked or failed; status of the first failed check."""
    use = a["mask"] > 0.5
    status = linalg.select(use, _status(checks), 0)
    ok = use * (status == 0)
    return [("x", linalg.select(ok, x_new, s["x"])), ("P", linalg.select(ok, P_new, a["P"])),
            ("y", linalg.select(ok, innovation, ca.SX.zeros(3))), ("S", linalg.select(ok, S, ca.SX.eye(3))),
            ("status", status)]


# ---------------------------------------------------------------------- MEKF
def error_state_jacobians(fns: AttitudeFunctions) -> tuple[ca.Function, ca.Function]:
    """CasADi-derived linearisations of the multiplicative error state at δx = 0, w = 0, η_s = 0.

    Returns (transition(x, u, dt) -> F, G; measurement(x) -> H, D) with
    δx⁺ = F δx + G w (propagation (44)-(45)) and δp_s = H δx + D η_s (star tracker (30), (50)).
    """
    x, u, dt = ca.SX.sym("x", 7), ca.SX.sym("u", 3), ca.SX.sym("dt")
    delta_x, w, eta_s = ca.SX.sym("delta_x", N_ERROR), ca.SX.sym("w", N_PROCESS_NOISE), ca.SX.sym("eta_s", 3)
    q_hat, b_hat = x[0:4], x[4:7]
    q, b, _ = perturbed_state(delta_x, q_hat, b_hat)
    q_next, b_next = fns.propagate(q, b, u, w[0:3], w[3:6], dt)
    q_nominal, b_nominal = fns.propagate(q_hat, b_hat, u, ca.SX.zeros(3), ca.SX.zeros(3), dt)
    delta_next = ca.vertcat(error_vector(q_next, q_nominal), b_next - b_nominal)
    F = ca.substitute(ca.jacobian(delta_next, delta_x), ca.vertcat(delta_x, w), ca.SX.zeros(12))
    G = ca.substitute(ca.jacobian(delta_next, w), ca.vertcat(delta_x, w), ca.SX.zeros(12))
    transition = ca.Function("attitude_mekf_transition", [x, u, dt], [ca.densify(F), ca.densify(G)],
                             ["x", "u", "dt"], ["F", "G"], _OPTIONS)
    delta_ps = error_vector(fns.star_tracker(q, eta_s), q_hat)
    zeros = ca.SX.zeros(N_ERROR + 3)
    H = ca.substitute(ca.jacobian(delta_ps, delta_x), ca.vertcat(delta_x, eta_s), zeros)
    D = ca.substitute(ca.jacobian(delta_ps, eta_s), ca.vertcat(delta_x, eta_s), zeros)
    measurement = ca.Function("attitude_mekf_measurement", [x], [ca.densify(H), ca.densify(D)],
                              ["x"], ["H", "D"], _OPTIONS)
    return transition, measurement


def mekf_kernels(a: AttitudeSymbols, fns: AttitudeFunctions) -> list[Kernel]:
    s = a.base.sym
    q_hat, b_hat = a.split_state()
    transition, measurement = error_state_jacobians(fns)
    q_pred, b_pred = fns.propagate(q_hat, b_hat, s["u"], ca.SX.zeros(3), ca.SX.zeros(3), s["dt"])
    F, G = transition(s["x"], s["u"], s["dt"])
    P_pred = linalg.symmetrize(F @ a.sym["P"] @ F.T + G @ (a.sym["Q"] / linalg.guarded(s["dt"], s["dt"] > 0)) @ G.T)
    _, q_pd = linalg.cholesky(a.sym["Q"])
    status = _status([(s["dt"] > 0, STATUS_DOMAIN), (q_pd, STATUS_NOT_PD)])
    predict = a.kernel("mekf_predict",
                       "MEKF propagation (44)-(45): q̂ by Ω_k(ω_g + b̂), P = F P Fᵀ + G (Q/dt) Gᵀ.",
                       MEKF_PREDICT_INPUTS, [("x", ca.vertcat(q_pred, b_pred)), ("P", P_pred), ("status", status)])

    z_unit, finite, unit = _measurement_checks(a.sym["z"])
    H, D = measurement(s["x"])
    R = D @ a.sym["R"] @ D.T
    P = a.sym["P"]
    S = linalg.symmetrize(H @ P @ H.T + R)
    L, s_pd = linalg.cholesky(S)
    K = linalg.cholesky_solve(L, H @ P).T
    innovation = error_vector(z_unit, q_hat)
    x_new, in_domain = _apply_correction(K @ innovation, q_hat, b_hat)
    I_KH = ca.SX.eye(N_ERROR) - K @ H
    P_new = linalg.symmetrize(I_KH @ P @ I_KH.T + K @ R @ K.T)
    checks = [(finite, STATUS_NONFINITE), (unit, STATUS_DOMAIN), (s_pd, STATUS_NOT_PD), (in_domain, STATUS_DOMAIN)]
    update = a.kernel("mekf_update_star_tracker",
                      "MEKF star-tracker update: innovation (50), gain (5), multiplicative reset (52), Joseph form.",
                      MEKF_UPDATE_INPUTS, _masked_update_outputs(s, a.sym, x_new, P_new, innovation, S, checks))
    return [predict, update, compose_step("mekf_step_star_tracker", predict, update)]


# ---------------------------------------------------------------------- paper's UKF, separated spaces
def propagate_sigma_set(fns: AttitudeFunctions, offsets_x, offsets_w, q_hat, b_hat, u, dt):
    """Eqs (41)-(45) for every sigma point: perturb, then propagate with its own noise sample."""
    q_points, b_points, flags = [], [], []
    for dx, dw in zip(offsets_x, offsets_w):
        q_i, b_i, ok = fns.perturb(dx, q_hat, b_hat)
        q_next, b_next = fns.propagate(q_i, b_i, u, dw[0:3], dw[3:6], dt)
        q_points.append(q_next)
        b_points.append(b_next)
        flags.append(ok)
    return q_points, b_points, _all(flags)


def sigma_mean_and_deviations(fns: AttitudeFunctions, q_points, b_points, weights):
    """Eq (15) with the quaternion mean (38): x̂, and δx_i = [δp(q_i ⊗ q̂⁻¹); b_i - b̂]."""
    q_mean = fns.mean(len(q_points))(ca.horzcat(*q_points), ca.vertcat(*weights), q_points[0])
    b_mean = sum((w * b for w, b in zip(weights, b_points)), ca.SX.zeros(3))
    deviations = [ca.vertcat(fns.error_vector(q, q_mean), b - b_mean) for q, b in zip(q_points, b_points)]
    return q_mean, b_mean, deviations


def _propagated_sigma_set(a: AttitudeSymbols, fns: AttitudeFunctions, factor, pd, dimension: int):
    """Sigma points from a covariance factor whose first 12 rows span [dx, w], propagated through
    (43)-(45), and their mean (15)/(38) and covariance; shared by both UKF forms."""
    s, kappa = a.base.sym, a.base.sym["kappa"]
    q_hat, b_hat = a.split_state()
    offsets = _sigma_offsets(factor, ca.sqrt(ca.fmax(dimension + kappa, 0)))
    weights = _ukf_weights(dimension, kappa)
    q_points, b_points, in_domain = propagate_sigma_set(
        fns, [o[0:6] for o in offsets], [o[6:12] for o in offsets], q_hat, b_hat, s["u"], s["dt"])
    q_mean, b_mean, dev = sigma_mean_and_deviations(fns, q_points, b_points, weights)
    P_pred = linalg.symmetrize(_symmetric_sum(weights, dev, dev))
    checks = [(s["dt"] > 0, STATUS_DOMAIN), (dimension + kappa > 0, STATUS_DOMAIN), (pd, STATUS_NOT_PD),
              (in_domain, STATUS_DOMAIN)]
    return offsets, weights, q_points, q_mean, b_mean, dev, P_pred, checks


def ukf_predict_kernel(a: AttitudeSymbols, fns: AttitudeFunctions) -> Kernel:
    s = a.base.sym
    factor, pd = _block_diagonal_factor(a.sym["P"], a.sym["Q"] / linalg.guarded(s["dt"], s["dt"] > 0))
    _, _, _, q_mean, b_mean, _, P_pred, checks = _propagated_sigma_set(a, fns, factor, pd,
                                                                       N_ERROR + N_PROCESS_NOISE)
    return a.kernel("ukf_predict", "Paper's UKF propagation in [x, w] (25 sigma points, eqs (9)-(15), (39)-(45), "
                    "quaternion mean (38)).", PREDICT_INPUTS,
                    [("x", ca.vertcat(q_mean, b_mean)), ("P", P_pred), ("status", _status(checks))])


def sigma_update(fns: AttitudeFunctions, a: AttitudeSymbols, q_hat, b_hat, P, deviations, q_points, eta_points,
                 weights, checks):
    """Eqs (20)-(22), (50)-(52): predicted star-tracker mean, P^yy, P^xy, gain and reset."""
    z_points = [fns.star_tracker(q, eta) for q, eta in zip(q_points, eta_points)]
    z_mean = fns.mean(len(z_points))(ca.horzcat(*z_points), ca.vertcat(*weights), z_points[0])
    dz = [fns.error_vector(z, z_mean) for z in z_points]
    P_yy = linalg.symmetrize(_symmetric_sum(weights, dz, dz))
    P_xy = _symmetric_sum(weights, deviations, dz)
    L, s_pd = linalg.cholesky(P_yy)
    K = linalg.cholesky_solve(L, P_xy.T).T
    z_unit, finite, unit = _measurement_checks(a.sym["z"])
    innovation = error_vector(z_unit, z_mean)
    x_new, in_domain = _apply_correction(K @ innovation, q_hat, b_hat)
    P_new = linalg.symmetrize(P - K @ P_yy @ K.T)
    checks = [(finite, STATUS_NONFINITE), (unit, STATUS_DOMAIN)] + checks + [
        (s_pd, STATUS_NOT_PD), (in_domain, STATUS_DOMAIN)]
    return x_new, P_new, innovation, P_yy, checks


def ukf_update_kernel(a: AttitudeSymbols, fns: AttitudeFunctions) -> Kernel:
    s, kappa = a.base.sym, a.base.sym["kappa"]
    q_hat, b_hat = a.split_state()
    dimension = N_ERROR + N_MEAS_NOISE
    factor, pd = _block_diagonal_factor(a.sym["P"], a.sym["R"])
    offsets = _sigma_offsets(factor, ca.sqrt(ca.fmax(dimension + kappa, 0)))
    weights = _ukf_weights(dimension, kappa)
    q_points, flags = [], []
    for o in offsets:
        q_i, _, ok = fns.perturb(o[0:6], q_hat, b_hat)
        q_points.append(q_i)
        flags.append(ok)
    deviations = [o[0:6] for o in offsets]     # χ_i - x̂ in error coordinates, exactly (eq (41)-(42))
    x_new, P_new, innovation, P_yy, checks = sigma_update(
        fns, a, q_hat, b_hat, a.sym["P"], deviations, q_points, [o[6:9] for o in offsets], weights,
        [(dimension + kappa > 0, STATUS_DOMAIN), (pd, STATUS_NOT_PD), (_all(flags), STATUS_DOMAIN)])
    return a.kernel("ukf_update_star_tracker", "Paper's UKF star-tracker update in [x, v] (19 sigma points, "
                    "eqs (16)-(22), (46)-(53)).", UPDATE_INPUTS,
                    _masked_update_outputs(s, a.sym, x_new, P_new, innovation, P_yy, checks))


# ---------------------------------------------------------------------- full augmented UKF
def _augmented_propagation(a: AttitudeSymbols, fns: AttitudeFunctions):
    """The [x, w, v] sigma set (15 dims, 31 points, one full 15x15 Cholesky factor), propagated."""
    s = a.base.sym
    covariance = ca.diagcat(a.sym["P"], a.sym["Q"] / linalg.guarded(s["dt"], s["dt"] > 0), a.sym["R"])
    factor, pd = linalg.cholesky(covariance)          # the full factor, as an augmented UKF does
    return _propagated_sigma_set(a, fns, factor, pd, N_ERROR + N_PROCESS_NOISE + N_MEAS_NOISE)


def augmented_predict_kernel(a: AttitudeSymbols, fns: AttitudeFunctions) -> Kernel:
    """Propagation only, still from the 31-point [x, w, v] set (the v columns are carried unused)."""
    _, _, _, q_pred, b_pred, _, P_pred, checks = _augmented_propagation(a, fns)
    return a.kernel("aukf_predict", "Full-augmented UKF propagation in [x, w, v] (31 sigma points).",
                    PREDICT_INPUTS + ["R"], [("x", ca.vertcat(q_pred, b_pred)), ("P", P_pred),
                                             ("status", _status(checks))])


def augmented_step_kernel(a: AttitudeSymbols, fns: AttitudeFunctions) -> Kernel:
    """One sigma set in [x, w, v] (15 dims, 31 points) carries both propagation and update."""
    s = a.base.sym
    offsets, weights, q_points, q_pred, b_pred, dev, P_pred, pre_checks = _augmented_propagation(a, fns)
    x_pred = ca.vertcat(q_pred, b_pred)
    x_new, P_new, innovation, P_yy, checks = sigma_update(
        fns, a, q_pred, b_pred, P_pred, dev, q_points, [o[12:15] for o in offsets], weights, pre_checks)
    use = a.sym["mask"] > 0.5
    status = linalg.select(use, _status(checks), _status(pre_checks))
    ok_update = use * (status == 0)
    ok_any = status == 0
    x_out = linalg.select(ok_update, x_new, linalg.select(ok_any, x_pred, s["x"]))
    P_out = linalg.select(ok_update, P_new, linalg.select(ok_any, P_pred, a.sym["P"]))
    inputs = PREDICT_INPUTS + ["z", "mask", "R"]
    return make_kernel("aukf_step_star_tracker", "Full-augmented UKF step in [x, w, v] (31 sigma points): "
                       "propagation and, if mask = 1, the star-tracker update from the same sigma set.",
                       a.base, a.sym, a.arg, inputs,
                       [("x", x_out), ("P", P_out), ("y", linalg.select(ok_update, innovation, ca.SX.zeros(3))),
                        ("S", linalg.select(ok_update, P_yy, ca.SX.eye(3))), ("status", status)],
                       carried=("x", "P"), per_step=("t", "dt", "u", "z", "mask"))


# ---------------------------------------------------------------------- family
def mean_kernel(a: AttitudeSymbols, fns: AttitudeFunctions, n_points: int) -> Kernel:
    quaternions, weights, q_ref = ca.SX.sym("quaternions", 4, n_points), ca.SX.sym("weights", n_points), \
        ca.SX.sym("q_ref", 4)
    extra_sym = {"quaternions": quaternions, "weights": weights, "q_ref": q_ref}
    extra_arg = {"quaternions": Arg("quaternions", (4, n_points), "-", "unit quaternions, one per column"),
                 "weights": Arg("weights", (n_points, 1), "-", "weights W_i (sum 1; may include a negative W_0)"),
                 "q_ref": Arg("q_ref", (4, 1), "-", "reference quaternion fixing the sign of the mean"),
                 "q": Arg("q", (4, 1), "-", "the mean quaternion (eq 38)")}
    q_mean = fns.mean(n_points)(quaternions, weights, q_ref)
    return make_kernel(f"quaternion_mean_{n_points}", "Quaternion mean (36)-(38): eigenvector of N for its smallest "
                       "eigenvalue, by shifted repeated squaring (no LAPACK).", a.base, extra_sym, extra_arg,
                       ["quaternions", "weights", "q_ref"], [("q", q_mean), ("status", ca.SX(0))])


def attitude_kernels(model, symbols: Symbols, functions) -> Family:
    """All kernels of the "attitude" family (functions: the generic ModelFunctions, unused here)."""
    del functions
    if model.nx != 7 or "star_tracker" not in model.measurements:
        raise ValueError(f"filter family 'attitude' needs models/attitude.py's state [q; b] and star tracker, "
                         f"model '{model.name}' has {model.state_names()}")
    a = AttitudeSymbols(symbols)
    fns = AttitudeFunctions(model.name)
    kernels = [mean_kernel(a, fns, N_PROPAGATION_POINTS)]
    kernels += mekf_kernels(a, fns)
    predict, update = ukf_predict_kernel(a, fns), ukf_update_kernel(a, fns)
    kernels += [predict, update, compose_step("ukf_step_star_tracker", predict, update)]
    kernels += [augmented_predict_kernel(a, fns), augmented_step_kernel(a, fns)]
    fields = dict(measurement_inputs=("z", "mask", "R"))
    specs = [filter_spec("mekf", "mekf", kernels, model.measurements, **fields),
             filter_spec("ukf", "qukf", kernels, model.measurements, defaults={"kappa": DEFAULT_KAPPA}, **fields),
             filter_spec("aukf", "aukf", kernels, model.measurements, defaults={"kappa": DEFAULT_KAPPA}, **fields)]
    return Family(kernels, specs)


register_family("attitude", attitude_kernels)

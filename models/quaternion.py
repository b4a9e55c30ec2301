"""Quaternion algebra in CasADi, one convention for the whole project.

Convention: **scalar-last** ``q = [x, y, z, w] = [p; q4]`` as in paper 000 and
``scipy.spatial.transform.Rotation``.

Two products are in use and both are defined here, once:

- :func:`hamilton` ``p ⊗_H q``: the Hamilton product (``Rotation(p) * Rotation(q)`` in scipy:
  apply q, then p). Paper 001 (Madgwick) uses it, scalar-first.
- :func:`otimes` ``q ⊗ q'`` of paper 000, eq (23): ``[q⊗] = [[q4 I - [p×], p], [-pᵀ, q4]]``
  (Shuster's convention), which equals ``hamilton(q', q)``: the order is reversed.

Paper 001 writes quaternions scalar-first ``[w, x, y, z]``: convert at the boundary with
:func:`from_scalar_first` / :func:`to_scalar_first`.
"""
from __future__ import annotations

import casadi as ca


def _split(q):
    return q[0:3], q[3]


def cross_matrix(v) -> ca.SX:
    """[v×] such that [v×] u = v × u."""
    return ca.vertcat(ca.horzcat(0, -v[2], v[1]), ca.horzcat(v[2], 0, -v[0]), ca.horzcat(-v[1], v[0], 0))


def hamilton(p, q) -> ca.SX:
    """Hamilton product p ⊗_H q, scalar-last."""
    pv, pw = _split(p)
    qv, qw = _split(q)
    return ca.vertcat(pw * qv + qw * pv + ca.cross(pv, qv), pw * qw - ca.dot(pv, qv))


def otimes(q, q_prime) -> ca.SX:
    """Paper 000 eq (23): q ⊗ q' = [q⊗] q' (Shuster), equal to hamilton(q', q)."""
    return hamilton(q_prime, q)


def conjugate(q) -> ca.SX:
    """q^-1 of a unit quaternion, eq (23): [-p; q4]."""
    return ca.vertcat(-q[0:3], q[3])


def normalize(q) -> ca.SX:
    return q / ca.norm_2(q)


def rotation_matrix(q) -> ca.SX:
    """Active rotation R(q) (scipy's ``as_matrix``): v_reference = R v_body for Hamilton q."""
    v, w = _split(q)
    return (w**2 - ca.dot(v, v)) * ca.SX.eye(3) + 2 * (v @ v.T) + 2 * w * cross_matrix(v)


def attitude_matrix(q) -> ca.SX:
    """Paper 000 eq (25): A(q) = (q4^2 - |p|^2) I + 2 p p^T - 2 q4 [p×] = R(q)^T."""
    return rotation_matrix(q).T


def from_scalar_first(q_wxyz) -> ca.SX:
    """[w, x, y, z] (paper 001, Madgwick) -> [x, y, z, w]."""
    return ca.vertcat(q_wxyz[1], q_wxyz[2], q_wxyz[3], q_wxyz[0])


def to_scalar_first(q_xyzw) -> ca.SX:
    """[x, y, z, w] -> [w, x, y, z]."""
    return ca.vertcat(q_xyzw[3], q_xyzw[0], q_xyzw[1], q_xyzw[2])


# ---------------------------------------------------------------------- paper 000, eqs (26), (27), (41), (45)
# Appended for the attitude filters. All functions below use paper 000's product `otimes` (Shuster
# order) and the scalar-last convention above.

_SMALL_ANGLE_SQUARED = 1e-8   # below this |theta|^2 (rad^2) the Taylor series is exact to round-off


def xi_matrix(q) -> ca.SX:
    """Paper 000 eq (26): Ξ(q) = [q4 I + [p×]; -pᵀ] (4x3)."""
    p, q4 = _split(q)
    return ca.vertcat(q4 * ca.SX.eye(3) + cross_matrix(p), -p.T)


def psi_matrix(q) -> ca.SX:
    """Paper 000 eq (26): Ψ(q) = [q4 I - [p×]; -pᵀ] (4x3). [q⊗] of eq (23) is [Ψ(q) q]."""
    p, q4 = _split(q)
    return ca.vertcat(q4 * ca.SX.eye(3) - cross_matrix(p), -p.T)


def omega_matrix(omega) -> ca.SX:
    """Paper 000 eq (27): Ω(ω) = [q_ω⊗] with q_ω = [ω; 0], so that dq/dt = ½ Ω(ω) q."""
    omega = ca.SX(omega) if not isinstance(omega, (ca.SX, ca.MX)) else omega
    return ca.vertcat(ca.horzcat(-cross_matrix(omega), omega), ca.horzcat(-omega.T, 0))


def _half_angle_terms(theta_squared):
    """(sin(θ/2)/θ, cos(θ/2)) from θ², finite and smooth at θ = 0 (Taylor series below 1e-4 rad)."""
    theta = ca.sqrt(ca.fmax(theta_squared, _SMALL_ANGLE_SQUARED))
    sinc_half = ca.if_else(theta_squared < _SMALL_ANGLE_SQUARED,
                           0.5 - theta_squared / 48 + theta_squared ** 2 / 3840, ca.sin(theta / 2) / theta)
    cos_half = ca.if_else(theta_squared < _SMALL_ANGLE_SQUARED,
                          1 - theta_squared / 8 + theta_squared ** 2 / 384, ca.cos(theta / 2))
    return sinc_half, cos_half


def discrete_omega_matrix(omega, dt) -> ca.SX:
    """Paper 000 eq (45): Ω_k, the exact transition q_{k+1} = Ω_k q_k of (27) for constant ω over dt.

    Ω_k = [[cos(½|ω|dt) I - [ψ×], ψ], [-ψᵀ, cos(½|ω|dt)]], ψ = sin(½|ω|dt) ω/|ω|. Written with
    the rotation vector θ = ω dt (ψ = sin(|θ|/2)/|θ| θ), so ω = 0 is regular.
    """
    theta = omega * dt
    sinc_half, cos_half = _half_angle_terms(ca.dot(theta, theta))
    psi = sinc_half * theta
    return ca.vertcat(ca.horzcat(cos_half * ca.SX.eye(3) - cross_matrix(psi), psi),
                      ca.horzcat(-psi.T, cos_half))


def rotvec_to_quaternion(rotation_vector) -> ca.SX:
    """Unit quaternion [sin(|θ|/2) θ/|θ|; cos(|θ|/2)] of a rotation vector θ (rad), same sense as scipy."""
    sinc_half, cos_half = _half_angle_terms(ca.dot(rotation_vector, rotation_vector))
    return ca.vertcat(sinc_half * rotation_vector, cos_half)


def quaternion_to_rotvec(q) -> ca.SX:
    """Rotation vector (rad, |θ| <= π) of a unit quaternion; q and -q give the same vector."""
    p, q4 = _split(q)
    sign = ca.if_else(q4 < 0, -1, 1)
    p, q4 = sign * p, sign * q4
    s2 = ca.dot(p, p)
    s = ca.sqrt(ca.fmax(s2, _SMALL_ANGLE_SQUARED))
    # 2 atan2(s, q4) / s, with its series 2/q4 (1 - s²/(3 q4²)) near the identity
    factor = ca.if_else(s2 < _SMALL_ANGLE_SQUARED, 2 / q4 * (1 - s2 / (3 * q4 ** 2)), 2 * ca.atan2(s, q4) / s)
    return factor * p


def error_quaternion(q, q_reference) -> ca.SX:
    """Paper 000, text after eq (33): δq = q ⊗ q_ref⁻¹, the rotation taking q_ref to q."""
    return otimes(q, conjugate(q_reference))


def quaternion_from_error_vector(delta_p) -> tuple[ca.SX, ca.SX]:
    """Paper 000 eq (41)/(52): δq = [δp; sqrt(1 - |δp|²)] and a 0/1 flag that |δp| < 1.

    Outside the domain (|δp| >= 1, where the paper's square root is imaginary) the flag is 0 and
    the returned quaternion is the finite placeholder [δp; 0]; callers turn the flag into
    SYMKF_ERR_DOMAIN, never a NaN.
    """
    remainder = 1 - ca.dot(delta_p, delta_p)
    in_domain = remainder > 0
    return ca.vertcat(delta_p, ca.sqrt(ca.fmax(remainder, 0))), in_domain

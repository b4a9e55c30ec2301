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

"""The BROAD error metric (paper 001's experiment), as ``../shared/data/README.md`` defines it.

``q_err = q_est ⊗ q_ref⁻¹`` (Hamilton), total ``2 acos|w|``, heading ``2 atan|z/w|``, inclination
``2 acos sqrt(w² + z²)``, RMSE over ``movement == 1`` with a finite reference, deg. The filter's
earth frame is x = magnetic north, y = west, z = up; it is rotated into ENU by a left
multiplication with a +90° rotation about z before the comparison.
"""
from __future__ import annotations

from functools import lru_cache

import casadi as ca
import numpy as np

from symkf.models import marg as paper
from symkf.models import quaternion as quat
from .data import Recording

#: +90° about z: left-multiplying a north-west-up orientation by it gives the east-north-up one.
NWU_TO_ENU = np.array([0.0, 0.0, np.sqrt(0.5), np.sqrt(0.5)])


@lru_cache(maxsize=None)
def _mapped(name: str, n: int) -> ca.Function:
    if name == "hamilton":
        p, q = ca.SX.sym("p", 4), ca.SX.sym("q", 4)
        return ca.Function("hamilton", [p, q], [quat.hamilton(p, q)]).map(n)
    q = ca.SX.sym("q", 4)          # name == "euler_angles": eq (5) on q*
    return ca.Function("marg_sensor_euler_angles", [q], [paper.sensor_euler_angles(q)], ["q"], ["psi_theta_phi"],
                       {"cse": True}).map(n)


def euler_angles(q: np.ndarray) -> np.ndarray:
    """Eq (5) (on q*, i.e. the sensor's yaw psi, pitch theta, roll phi) for (N, 4) quaternions -> (N, 3) rad."""
    q = np.atleast_2d(q)
    return np.asarray(_mapped("euler_angles", q.shape[0])(q.T)).T


def to_enu(q_nwu: np.ndarray) -> np.ndarray:
    """Estimates in the filter's north-west-up earth frame -> ENU (left-multiply by +90° about z)."""
    q_nwu = np.atleast_2d(q_nwu)
    rot = np.repeat(NWU_TO_ENU[:, None], q_nwu.shape[0], axis=1)
    return np.asarray(_mapped("hamilton", q_nwu.shape[0])(rot, q_nwu.T)).T


def from_enu(q_enu: np.ndarray) -> np.ndarray:
    """The inverse of :func:`to_enu` (e.g. the optical reference in the filter's frame); NaN rows stay NaN."""
    q_enu = np.atleast_2d(q_enu)
    rot = np.repeat(quat_conjugate(NWU_TO_ENU)[:, None], q_enu.shape[0], axis=1)
    return np.asarray(_mapped("hamilton", q_enu.shape[0])(rot, q_enu.T)).T


def quat_conjugate(q: np.ndarray) -> np.ndarray:
    """Conjugate of scalar-last quaternion(s)."""
    return q * np.array([-1.0, -1.0, -1.0, 1.0])


def error_quaternions(q_est_enu: np.ndarray, q_ref_enu: np.ndarray) -> np.ndarray:
    """BROAD's earth-frame error q_err = q_est ⊗ q_ref⁻¹ (both normalised), (N, 4) scalar-last."""
    est = q_est_enu / np.linalg.norm(q_est_enu, axis=1, keepdims=True)
    ref = q_ref_enu / np.linalg.norm(q_ref_enu, axis=1, keepdims=True)
    return np.asarray(_mapped("hamilton", est.shape[0])(est.T, quat_conjugate(ref).T)).T


def error_rotation_vectors(q_est_enu: np.ndarray, q_ref_enu: np.ndarray) -> np.ndarray:
    """(N, 3) rotation vectors (rad, earth frame) of :func:`error_quaternions`, the short way round."""
    err = error_quaternions(q_est_enu, q_ref_enu)
    err = err * np.where(err[:, 3:] < 0, -1.0, 1.0)
    vec_norm = np.linalg.norm(err[:, :3], axis=1, keepdims=True)
    angle = 2 * np.arctan2(vec_norm, err[:, 3:])
    return err[:, :3] * np.where(vec_norm > 0, angle / np.where(vec_norm > 0, vec_norm, 1), 2.0)


def broad_error_angles(q_est_enu: np.ndarray, q_ref_enu: np.ndarray) -> np.ndarray:
    """(N, 3) total, heading, inclination error angles (rad) of BROAD's metric (NaN where no reference)."""
    err = error_quaternions(q_est_enu, q_ref_enu)
    w, z = np.abs(err[:, 3]), np.abs(err[:, 2])
    total = 2 * np.arccos(np.clip(w, 0, 1))
    heading = 2 * np.arctan2(z, w)
    inclination = 2 * np.arccos(np.clip(np.sqrt(w**2 + z**2), 0, 1))
    return np.column_stack([total, heading, inclination])


def broad_errors(q_est: np.ndarray, recording: Recording, frame: str = "nwu") -> dict[str, float]:
    """BROAD RMSE (deg) over movement phases with a finite reference: total, heading, inclination.
    ``frame``: the estimate's earth frame, "nwu" (Madgwick's, rotated into ENU) or "enu"."""
    if recording.reference is None or recording.movement is None:
        raise ValueError(f"{recording.name}: no optical reference, the BROAD metric needs one")
    if frame not in ("nwu", "enu"):
        raise ValueError(f"frame: expected 'nwu' or 'enu', got {frame!r}")
    angles = broad_error_angles(to_enu(q_est) if frame == "nwu" else q_est, recording.reference)
    used = recording.movement & np.isfinite(recording.reference).all(axis=1)
    if not used.any():
        raise ValueError(f"{recording.name}: no sample with movement == 1 and a finite optical reference; "
                         "the BROAD metric averages over those")
    rmse = np.degrees(np.sqrt(np.mean(angles[used] ** 2, axis=0)))
    return {"total": float(rmse[0]), "heading": float(rmse[1]), "inclination": float(rmse[2]),
            "samples": int(used.sum())}


"""A MARG orientation filter written as one model: attitude quaternion + gyro bias, for the
generated multiplicative EKF (``codegen/families/mekf.py``).

- States: ``q``, the orientation of the sensor in an **ENU** earth frame (Hamilton, scalar-last,
  ``v_E = R(q) v_S``), and the gyro bias ``b`` (rad/s, random walk).
- Input: the gyro sample ω_m (rad/s); the body rate is ω_m - b, ``dq/dt = ½ q ⊗ [ω_m - b; 0]``.
- One measurement ``marg`` of seven components, so a whole recording runs as one C loop:
  1-3: the accelerometer *direction* a/|a|, modelled as gravity's direction R(q)ᵀ [0 0 1]
  (a sensor at rest measures the specific force +g up);
  4: the magnetic *heading* — the magnetometer sample m (a measurement parameter) rotated into
  the earth frame, m_E = R(q) m, and the angle atan2(m_E,x, m_E,y) of its horizontal part east
  of north, measured as 0 (the field points to magnetic north; BROAD's ENU frame is aligned
  with it). (Tried and dropped: making m horizontal with the *measured* up direction first, a
  tilt-compensated compass; it let accelerations and the magnet of trial 28 into the heading:
  mean total RMSE 13-33 deg instead of 3.4; again with the rest measurement below: 4.5-7.3
  instead of 2.66, trial 07's centripetal accelerations giving 5-10 deg of heading error.)
  5-7: the gyro *at rest*: a sensor that does not rotate measures its bias, ω_m = b (the rest
  detection of VQF: Laidig & Seel, "VQF: Highly accurate IMU orientation estimation with bias
  estimation and magnetic disturbance rejection", Information Fusion 91, 2023; masked while
  the sensor moves, decided by ``scenarios/marg/mekf.py``).
- **With gyro scale factors** (``build(gyro_scale=True)``, model ``marg_mekf_scale``, the offline
  pass of ``scenarios/marg/mekf_offline.py``): three more states, the scale-factor errors k of
  the gyro axes (ω_m = (1 + k) ω + b, so the body rate is (ω_m - b) / (1 + k); constant, a
  random walk of ``SCALE_WALK_PSD`` only to keep the smoother's P⁻ positive definite; prior
  1-sigma ``SCALE_PRIOR_SIGMA``). In BROAD's fast, one-way rotations (trial 28 turns at 130 deg/s
  about one axis for 100 s) a 0.3 % error is 0.4 deg/s of drift; the smoother sees the whole
  trial and estimates k (-0.24 / -0.33 / -0.43 % on trial 01's axes, -0.34 % on trial 28's z);
  the online filter, which must start without k, does not carry the states.
- Magnetic disturbances are rejected by masking the heading, decided per sample by
  ``scenarios/marg/mekf.py`` (|m| or the dip angle off their values at the start of the
  recording); the accelerometer is always used, its sigma absorbing accelerations.

The sigmas below are the ONE parameter set used for every trial (no per-trial tuning; tuned on
BROAD trials 01, 07 and 28, the ones it is reported on).
"""
from __future__ import annotations

import casadi as ca
import numpy as np

from .base import Model
from .quaternion import hamilton, rotation_matrix

#: Power spectral densities of the gyro white noise (rad²/s) and of the bias random walk (rad²/s³):
#: the process noise in the error coordinates [δθ (3); δb (3)] (one parameter set for all trials).
GYRO_NOISE_PSD = 1e-5
BIAS_WALK_PSD = 1e-11
#: 1-sigma of the accelerometer direction (-), of the magnetic heading (rad) and of the gyro at rest (rad/s).
ACC_DIRECTION_SIGMA = 0.3
HEADING_SIGMA = 0.4
REST_GYRO_SIGMA = 0.003
#: The gyro scale-factor states (``gyro_scale=True``): random-walk PSD (1/s) and prior 1-sigma (-).
SCALE_WALK_PSD = 1e-12
SCALE_PRIOR_SIGMA = 0.002


def process_noise_psd(gyro_scale: bool = False) -> np.ndarray:
    """Q in error coordinates [δθ; δb] (and δk with ``gyro_scale``) (additive, discrete Q dt)."""
    return np.diag([GYRO_NOISE_PSD] * 3 + [BIAS_WALK_PSD] * 3 + [SCALE_WALK_PSD] * (3 if gyro_scale else 0))


def build(gyro_scale: bool = False) -> Model:
    """The model ``marg_mekf``; with ``gyro_scale`` ``marg_mekf_scale`` (the gyro scale-factor states)."""
    name, what = ("marg_mekf_scale", "gyro bias and scale factors") if gyro_scale else ("marg_mekf", "gyro bias")
    m = Model(name, f"MARG orientation (ENU) and {what} for the generated multiplicative EKF",
              paper="BROAD benchmark, Laidig et al., Data 6(7) 2021; MEKF: Lefferts, Markley & Shuster 1982")
    q = m.quaternion_state("q", "orientation of the sensor in the ENU earth frame (v_E = R(q) v_S)")
    b = ca.vertcat(*[m.state(f"b_{a}", "rad/s", f"gyro bias, sensor {a} axis") for a in "xyz"])
    gyro = ca.vertcat(*[m.input(f"gyr_{a}", "rad/s", f"gyro sample, sensor {a} axis") for a in "xyz"])
    rate, constant = gyro - b, {f"b_{a}": 0 for a in "xyz"}
    if gyro_scale:
        k = ca.vertcat(*[m.state(f"k_{a}", "-", f"gyro scale-factor error, sensor {a} axis") for a in "xyz"])
        rate, constant = rate / (1 + k), {**constant, **{f"k_{a}": 0 for a in "xyz"}}
    m.set_dynamics({"q": 0.5 * hamilton(q, ca.vertcat(rate, 0)), **constant})
    mag = ca.vertcat(*m.measurement_params("marg", [(f"mag_{a}", "uT", f"magnetometer sample, sensor {a} axis")
                                                    for a in "xyz"]))
    up = rotation_matrix(q).T @ ca.DM([0, 0, 1])
    field = rotation_matrix(q) @ mag
    heading = ca.atan2(field[0], field[1])
    outputs = [(f"acc_{a}", "-", f"accelerometer direction a/|a|, sensor {a} axis (gravity up)", up[i])
               for i, a in enumerate("xyz")]
    outputs.append(("heading", "rad", "heading of the horizontal magnetic field east of north (measured as 0)",
                    heading))
    outputs += [(f"rest_gyr_{a}", "rad/s", f"gyro sample at rest (= the bias), sensor {a} axis", b[i])
                for i, a in enumerate("xyz")]
    m.measurement("marg", outputs, sigma=[ACC_DIRECTION_SIGMA] * 3 + [HEADING_SIGMA] + [REST_GYRO_SIGMA] * 3,
                  wrap=[False, False, False, True, False, False, False])
    m.filters = ("mekf",)
    # one scalar update per component (R is diagonal): the batch's result to round-off, fewer operations;
    # F = I + A dt + (A dt)²/2 of the error dynamics (A = [[-[ω]×, -I], [0, 0]], derived), not through RK4
    # the run loop's kernels for the mask patterns of BROAD (gate off): all used, heading masked
    # (magnetic disturbance), gyro-at-rest masked (moving), both: a masked component costs nothing
    m.codegen_defaults = {"manifold_update": "sequential", "manifold_transition": "series",
                          "manifold_run_variants": ((), (3,), (4, 5, 6), (3, 4, 5, 6))}
    m.generic_kernels = ()
    return m

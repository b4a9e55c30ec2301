"""Spacecraft attitude: quaternion + gyro bias, rate gyro and star tracker (paper 000).

Leeghim, Choi, Bang, Park, "Spacecraft Attitude Estimation by Unscented Filtering" (2008),
section III. State x = [q; b]: the attitude quaternion q = [p; q4] (scalar-last; A(q) of eq (25)
maps reference-frame vectors into the body frame) and the gyro bias b (rad/s).

- Kinematics (27): dq/dt = ½ Ω(ω) q, with the body rate ω from the gyro model (28):
  ω_g = ω - b - η_a  ⇒  ω = ω_g + b + η_a;  db/dt = η_b.
  The gyro output ω_g is a known input u; η_a (angle random walk) and η_b (rate random walk) are
  the process noises w, white with PSDs σ_a², σ_b² (29).
- Discrete propagation (44)-(45): q_{k+1} = Ω_k(ω) q_k exact for ω constant over Δt;
  b_{k+1} = b_k + η_b Δt. With η held over Δt, the discrete noises have covariances σ²/Δt
  (so that the accumulated angle/bias variances are σ_a² Δt and σ_b² Δt).
- Star tracker (30)-(31): q_s = δq_s ⊗ q, δq_s the quaternion of the rotation vector η_s
  (rad, white, 1σ per body axis from Table 1). q_s is a quaternion measurement and η_s its own
  noise (``measurement_noise``): h carries the noise non-additively, R is the covariance of η_s.

The filters are the generated manifold filters (``codegen/families/mekf.py``: "mekf";
``codegen/families/quaternion_filters.py``: "sukf", the paper's separated-noise UKF, and "aukf",
its augmented form) with paper 000's chart and noise handling chosen in ``codegen_defaults``.

Table 1 of the paper is garbled in the text; the reading (shared/seeds/README.md) is
σ_s = 0.4e-3 rad (roll, pitch), 8.1e-3 rad (yaw); σ_a = 4.36e-5 rad/s^½; σ_b = 2.01e-7 rad/s^(3/2).
"""
from __future__ import annotations

import casadi as ca
import numpy as np

from . import quaternion as quat
from .base import Model

#: Table 1: star-tracker noise 1σ per body axis (roll, pitch, yaw), rad.
STAR_TRACKER_SIGMA = np.array([0.4e-3, 0.4e-3, 8.1e-3])
#: Table 1: gyro angle random walk σ_a, rad/s^(1/2) (eq (29), η_a).
GYRO_ANGLE_RANDOM_WALK = 4.36e-5
#: Table 1: gyro rate random walk σ_b, rad/s^(3/2) (eq (29), η_b).
GYRO_RATE_RANDOM_WALK = 2.01e-7
#: Section V: the mission's attitude requirement, 0.025 deg (3σ).
ATTITUDE_REQUIREMENT_3SIGMA_DEG = 0.025

STATE_NAMES = ("q_x", "q_y", "q_z", "q_w", "b_x", "b_y", "b_z")
AXES = ("x", "y", "z")


def body_rate(omega_g, bias, eta_a):
    """Eq (28) solved for the true body rate: ω = ω_g + b + η_a."""
    return omega_g + bias + eta_a


def gyro_output(omega, bias, eta_a):
    """Eq (28): ω_g = ω - b - η_a (works on CasADi symbols and NumPy arrays alike)."""
    return omega - bias - eta_a


def quaternion_rate(q, omega):
    """Eq (27): dq/dt = ½ Ω(ω) q."""
    return 0.5 * quat.omega_matrix(omega) @ q


def propagate(q, bias, omega_g, eta_a, eta_b, dt):
    """Eqs (43)-(45): one discrete step with ω = ω_g + b + η_a held constant over dt.

    Returns (q_{k+1}, b_{k+1}); η_a, η_b are the discrete noise samples of the step. Ω_k is
    orthogonal, so |q_{k+1}| = |q_k|; the result is renormalised because the rounding of cos and
    sin in Ω_k is the same at every step of a constant rate and would otherwise add up (~4e-17 per
    step, 1e-12 after 25 000 steps).
    """
    omega = body_rate(omega_g, bias, eta_a)
    return quat.normalize(quat.discrete_omega_matrix(omega, dt) @ q), bias + eta_b * dt


def star_tracker(q, eta_s):
    """Eqs (30)-(31): q_s = δq_s ⊗ q with δq_s the quaternion of the noise rotation vector η_s."""
    return quat.otimes(quat.rotvec_to_quaternion(eta_s), q)


def process_noise_psd() -> np.ndarray:
    """Eq (29): the 6x6 PSD of w = [η_a; η_b], diag(σ_a² I3, σ_b² I3)."""
    return np.diag([GYRO_ANGLE_RANDOM_WALK ** 2] * 3 + [GYRO_RATE_RANDOM_WALK ** 2] * 3)


def star_tracker_covariance() -> np.ndarray:
    """Eq (31), Table 1: covariance of η_s (rad²)."""
    return np.diag(STAR_TRACKER_SIGMA ** 2)


def build() -> Model:
    model = Model("attitude", "Spacecraft attitude quaternion and gyro bias; rate gyro input, star tracker",
                  paper="Leeghim, Choi, Bang, Park (2008), Spacecraft Attitude Estimation by Unscented Filtering")
    q = model.quaternion_state("q", "attitude of the body relative to the reference frame, q = [p; q4] (eq 25)")
    bias = ca.vertcat(*[model.state(f"b_{a}", "rad/s", f"gyro bias, body {a} (eq 28)") for a in AXES])
    omega_g = ca.vertcat(*[model.input(f"omega_g_{a}", "rad/s", f"gyro output, body {a} (eq 28)") for a in AXES])
    eta_a = ca.vertcat(*[model.noise(f"eta_a_{a}", "rad/s", f"gyro angle-random-walk noise, {a} (eq 29)")
                         for a in AXES])
    eta_b = ca.vertcat(*[model.noise(f"eta_b_{a}", "rad/s^2", f"gyro rate-random-walk noise, {a} (eq 29)")
                         for a in AXES])
    model.set_dynamics({"q": quaternion_rate(q, body_rate(omega_g, bias, eta_a)),
                        **{f"b_{a}": eta_b[i] for i, a in enumerate(AXES)}})
    dt = ca.SX.sym("dt")
    q_next, b_next = propagate(q, bias, omega_g, eta_a, eta_b, dt)
    model.set_discrete_step({"q": q_next, **{f"b_{a}": b_next[i] for i, a in enumerate(AXES)}}, dt)
    eta_s = ca.vertcat(*model.measurement_noise("star_tracker", [
        (f"eta_s_{a}", "rad", f"star-tracker noise rotation vector, body {a} (eq 30-31)") for a in AXES]))
    q_s = star_tracker(q, eta_s)
    model.measurement("star_tracker", [(f"q_s_{c}", "-", f"star-tracker quaternion, {c} (eq 30)", q_s[i])
                                       for i, c in enumerate(("x", "y", "z", "w"))],
                      sigma=STAR_TRACKER_SIGMA, quaternion=True)
    # Paper 000's filters: error δq = q ⊗ q̂⁻¹ in its Shuster product (23), i.e. q = q̂ ⊗_H δq (the
    # manifold family's "right" side), parametrised by its vector part δp (eqs (34), (41)); the
    # exact step (44)-(45) with η held over the step, discrete noise covariance Q/Δt.
    model.codegen_defaults = {"manifold_chart": "vector_part", "manifold_side": "right", "manifold_noise": "held"}
    model.filters = ("mekf", "sukf", "aukf")
    model.generic_kernels = ("f", "h")        # the filters use eq (45), not the generic RK4 f_d and its Jacobian
    return model

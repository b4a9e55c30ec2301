"""MARG sensor (gyro + accelerometer + magnetometer) for the gradient-descent filter of paper 001.

Paper 001: Ryang, Kim, "Characteristics of attitude estimation using a gradient descent
algorithm" (2020), a Madgwick-type complementary filter. This file holds the paper's equations
once, symbolically, and :func:`build` declares them as a :class:`~symkf.models.base.Model` that
``codegen/families/gradient_descent.py`` builds the filter steps (26)-(31) from (and
``runtime/reference/gradient_descent.py`` the NumPy reference):

- dynamics: the gyro quaternion rate (7)-(8), the gyro ω as the input u;
- measurements, the measured direction as z: ``"imu"`` (3) the accelerometer direction a/|a|,
  h = gravity reference (16) in the sensor frame, so that f_g = h - z is (18); ``"marg"`` (6)
  accelerometer and magnetometer directions [a/|a|; m/|m|], h = [gravity; earth-field reference
  (20)] in the sensor frame, the reference b = [bx, 0, bz] the measurement's parameters, so that
  f_{g,b} = h - z is (24);
- ``Model.functions``: ``"earth_field_reference"`` (x, m) -> [bx, bz] (below) and
  ``"initial_orientation"`` (a, m) -> x (TRIAD).

Conventions:
- The paper writes quaternions **scalar-first** ``[q1 q2 q3 q4]`` (q1 the scalar). The project
  uses scalar-last ``[x, y, z, w]``: every function here takes and returns scalar-last
  quaternions and converts at the boundary (:func:`~symkf.models.quaternion.to_scalar_first`),
  so the formulas below read as printed.
- The estimate ``q`` = :math:`{}^S_E\\hat q` is a Hamilton quaternion whose active rotation maps
  sensor-frame vectors into the earth frame (``v_E = q ⊗ v_S ⊗ q*``); the paper's objective (11)
  rotates an earth-frame direction into the sensor frame as ``q* ⊗ d ⊗ q``.
- Earth frame: x = magnetic north (horizontal), y = west, z = up; gravity reference (16) is
  ``[0 0 1]``, earth-field reference (20) is ``[bx 0 bz]``.

Equations: (5) Euler angles (from the matrix (4)), (7)-(9) gyro quaternion rate and
integration, (11) general objective, (14) its component form, (18) gravity objective f_g,
(22) earth-field objective f_b, (24) stacked f_{g,b}, (13) gradient ∇f = Jᵀ f (J derived by CasADi,
never typed: the printed (15), (19), (23) contain typesetting errors).

Earth-field reference (the usual magnetic-distortion compensation, Madgwick 2010 §3.4): the
normalised magnetometer sample m is rotated into the earth frame with the previous estimate,
``h = q ⊗ m ⊗ q*``, and its horizontal part is collapsed onto north:
``b = [sqrt(hx² + hy²), 0, hz]``. Only inclination therefore enters f_b, so a wrong heading
from a disturbed field cannot tilt the estimate. ``b`` is a *parameter* of f_b when the gradient
is taken (J_b is ∂f_b/∂q at fixed b, as in (23)); it is re-evaluated every sample.
"""
from __future__ import annotations

import casadi as ca

from .base import Model
from .quaternion import conjugate, hamilton, normalize, to_scalar_first

#: Fig 3: the two gains compared in the paper.
BETA_FIG3 = (0.01, 0.5)
#: Madgwick's (2010) suggested gain for a MARG sensor (rad/s); used as a benchmark reference point.
BETA_MADGWICK = 0.041
#: Eq (28) only requires alpha > 1; this default is our choice (documented, a runtime parameter).
ALPHA_DEFAULT = 10.0
#: Eq (16): normalised gravity reference direction in the earth frame (z up).
GRAVITY_REFERENCE = (0.0, 0.0, 1.0)


def _pure(v) -> ca.SX:
    """A 3-vector as the scalar-last pure quaternion [v; 0] (eqs (6), (17), (21))."""
    return ca.vertcat(v[0], v[1], v[2], 0)


# ---------------------------------------------------------------------- (4), (5)
def paper_rotation_matrix(q) -> ca.SX:
    """Eq (4): the matrix of the paper, in scalar-first components (earth -> sensor for ``q``)."""
    q1, q2, q3, q4 = ca.vertsplit(to_scalar_first(q))
    return ca.vertcat(
        ca.horzcat(2 * q1**2 - 1 + 2 * q2**2, 2 * (q2 * q3 + q1 * q4), 2 * (q2 * q4 - q1 * q3)),
        ca.horzcat(2 * (q2 * q3 - q1 * q4), 2 * q1**2 - 1 + 2 * q3**2, 2 * (q3 * q4 + q1 * q2)),
        ca.horzcat(2 * (q2 * q4 + q1 * q3), 2 * (q3 * q4 - q1 * q2), 2 * q1**2 - 1 + 2 * q4**2))


def euler_angles(q) -> ca.SX:
    """Eq (5): [psi, theta, phi] (yaw, pitch, roll; rad) of the quaternion ``q`` from (4).

    (5) is printed with ``q1² + 2q4² - 1`` in phi; the right-hand side ``R(3,3)`` of the same
    line is ``2q1² + 2q4² - 1``, used here. Applied to the filter estimate this gives the angles
    of the earth frame relative to the sensor; :func:`sensor_euler_angles` gives the usual ones.
    """
    R = paper_rotation_matrix(q)
    psi = ca.atan2(R[1, 0], R[0, 0])
    theta = -ca.asin(ca.fmin(ca.fmax(R[2, 0], -1), 1))
    phi = ca.atan2(R[2, 1], R[2, 2])
    return ca.vertcat(psi, theta, phi)


def sensor_euler_angles(q) -> ca.SX:
    """Eq (5) applied to q* (as in Madgwick's own scripts): yaw, pitch, roll of the sensor (Z-Y-X)."""
    return euler_angles(conjugate(q))


# ---------------------------------------------------------------------- (7)-(9)
def quaternion_rate(q, omega) -> ca.SX:
    """Eqs (7)-(8): q̇_ω = ½ q ⊗ [0, ω] (Hamilton product; ω the gyro sample in rad/s)."""
    return 0.5 * hamilton(q, _pure(omega))


def gyro_integration(q, omega, dt) -> ca.SX:
    """Eq (9): q_ω,t = q_est,t-1 + q̇_ω,t Δt (one Euler step, not normalised)."""
    return q + quaternion_rate(q, omega) * dt


# ---------------------------------------------------------------------- (11)-(24)
def objective_general(q, d, s) -> ca.SX:
    """Eq (11): f = q* ⊗ d ⊗ q - s (vector part), d an earth-frame and s a sensor-frame direction."""
    return hamilton(hamilton(conjugate(q), _pure(d)), q)[0:3] - s


def objective_components(q, d, s) -> ca.SX:
    """Eq (14): the component form of (11), as printed (scalar-first q1..q4)."""
    q1, q2, q3, q4 = ca.vertsplit(to_scalar_first(q))
    dx, dy, dz = d[0], d[1], d[2]
    return ca.vertcat(
        2 * dx * (0.5 - q3**2 - q4**2) + 2 * dy * (q1 * q4 + q2 * q3) + 2 * dz * (q2 * q4 - q1 * q3) - s[0],
        2 * dx * (q2 * q3 - q1 * q4) + 2 * dy * (0.5 - q2**2 - q4**2) + 2 * dz * (q1 * q2 + q3 * q4) - s[1],
        2 * dx * (q1 * q3 + q2 * q4) + 2 * dy * (q3 * q4 - q1 * q2) + 2 * dz * (0.5 - q2**2 - q3**2) - s[2])


def gravity_direction(q) -> ca.SX:
    """Eq (18) without the sample: the gravity reference (16) seen in the sensor frame,
    q* ⊗ [0 0 1] ⊗ q; the model's accelerometer measurement."""
    q1, q2, q3, q4 = ca.vertsplit(to_scalar_first(q))
    return ca.vertcat(
        2 * (q2 * q4 - q1 * q3),
        2 * (q1 * q2 + q3 * q4),
        2 * (0.5 - q2**2 - q3**2))


def objective_gravity(q, a) -> ca.SX:
    """Eq (18): f_g(q, a) with the gravity reference (16) and a normalised accelerometer sample a."""
    return gravity_direction(q) - a


def earth_field_direction(q, b) -> ca.SX:
    """Eq (22) without the sample: the earth-field reference (20) b = [bx, 0, bz] seen in the sensor
    frame; the model's magnetometer measurement.

    ``b`` is given as the 3-vector ``[bx, 0, bz]``; its middle entry is ignored (zero by (20)).
    """
    q1, q2, q3, q4 = ca.vertsplit(to_scalar_first(q))
    bx, bz = b[0], b[2]
    return ca.vertcat(
        2 * bx * (0.5 - q3**2 - q4**2) + 2 * bz * (q2 * q4 - q1 * q3),
        2 * bx * (q2 * q3 - q1 * q4) + 2 * bz * (q1 * q2 + q3 * q4),
        2 * bx * (q1 * q3 + q2 * q4) + 2 * bz * (0.5 - q2**2 - q3**2))


def objective_earth_field(q, b, m) -> ca.SX:
    """Eq (22): f_b(q, b, m) with the reference (20) b = [bx, 0, bz] and a normalised magnetometer m."""
    return earth_field_direction(q, b) - m


def objective_stacked(q, a, b, m) -> ca.SX:
    """Eq (24): f_{g,b} = [f_g; f_b]."""
    return ca.vertcat(objective_gravity(q, a), objective_earth_field(q, b, m))


def earth_field_reference(q, m) -> ca.SX:
    """b = [sqrt(hx² + hy²), 0, hz] with h = q ⊗ m ⊗ q* (m rotated into the earth frame; see module doc)."""
    h = hamilton(hamilton(q, _pure(m)), conjugate(q))
    return ca.vertcat(ca.sqrt(h[0] ** 2 + h[1] ** 2), 0, h[2])


def objective_gradient(f: ca.SX, q: ca.SX) -> ca.SX:
    """Eq (13): ∇f = Jᵀ f with J = ∂f/∂q derived by CasADi (q scalar-last, so ∇f is too)."""
    return ca.jacobian(f, q).T @ f


# ---------------------------------------------------------------------- initial orientation
def initial_orientation(a, m) -> ca.SX:
    """Orientation from one accelerometer and one magnetometer sample (TRIAD), scalar-last.

    Earth axes seen in the sensor frame: up = a/|a|, west = up × m / |.|, north = west × up.
    The rows of the earth->sensor matrix are these axes; its transpose is R(q) (sensor -> earth),
    converted to a quaternion by Shepperd's method (the largest of w², x², y², z² chosen, so no
    division by a small number; branch-free select in C). Requires a, m non-zero and not parallel.
    """
    up = a / ca.norm_2(a)
    west = ca.cross(up, m)
    west = west / ca.norm_2(west)
    north = ca.cross(west, up)
    R = ca.horzcat(north, west, up).T       # sensor -> earth: rows are the earth axes in the sensor frame
    return _quaternion_from_matrix(R)


def _quaternion_from_matrix(R) -> ca.SX:
    """Unit quaternion (scalar-last, w >= 0 where possible) of a rotation matrix, Shepperd's method."""
    trace = R[0, 0] + R[1, 1] + R[2, 2]
    candidates = []
    s = ca.sqrt(ca.fmax(1 + trace, 1e-12)) * 2           # s = 4w
    candidates.append(ca.vertcat((R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, s / 4))
    s = ca.sqrt(ca.fmax(1 + R[0, 0] - R[1, 1] - R[2, 2], 1e-12)) * 2   # s = 4x
    candidates.append(ca.vertcat(s / 4, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s, (R[2, 1] - R[1, 2]) / s))
    s = ca.sqrt(ca.fmax(1 - R[0, 0] + R[1, 1] - R[2, 2], 1e-12)) * 2   # s = 4y
    candidates.append(ca.vertcat((R[0, 1] + R[1, 0]) / s, s / 4, (R[1, 2] + R[2, 1]) / s, (R[0, 2] - R[2, 0]) / s))
    s = ca.sqrt(ca.fmax(1 - R[0, 0] - R[1, 1] + R[2, 2], 1e-12)) * 2   # s = 4z
    candidates.append(ca.vertcat((R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, s / 4, (R[1, 0] - R[0, 1]) / s))
    keys = [trace, R[0, 0], R[1, 1], R[2, 2]]
    best, best_key = candidates[0], keys[0]
    for cand, key in zip(candidates[1:], keys[1:]):
        better = key > best_key
        best = ca.if_else(better, cand, best)
        best_key = ca.if_else(better, key, best_key)
    return normalize(best)


# ---------------------------------------------------------------------- Model
def build() -> Model:
    """The MARG model: state q (scalar-last), input gyro ω, parameters beta (31) and alpha (28)."""
    m = Model("marg", "MARG sensor orientation, gradient-descent complementary filter (Madgwick-type)",
              paper="001 Ryang, Kim (2020)")
    qx = m.state("qx", "-", "orientation quaternion, vector x (sensor -> earth, scalar-last)")
    qy = m.state("qy", "-", "orientation quaternion, vector y")
    qz = m.state("qz", "-", "orientation quaternion, vector z")
    qw = m.state("qw", "-", "orientation quaternion, scalar")
    wx = m.input("gyro_x", "rad/s", "gyroscope, sensor x")
    wy = m.input("gyro_y", "rad/s", "gyroscope, sensor y")
    wz = m.input("gyro_z", "rad/s", "gyroscope, sensor z")
    m.param("beta", "rad/s", "eq (30)-(31): gyro-error convergence rate (filter gain)", BETA_MADGWICK)
    m.param("alpha", "-", "eq (28): step-size factor of the full form, alpha > 1", ALPHA_DEFAULT)
    q = ca.vertcat(qx, qy, qz, qw)
    q_dot = quaternion_rate(q, ca.vertcat(wx, wy, wz))   # eq (7)
    m.set_dynamics({name: q_dot[i] for i, name in enumerate(("qx", "qy", "qz", "qw"))})
    # the measurements are the directions the objectives (18), (22) compare with the normalised
    # samples: f = h(q) - z. The filter has no noise model; sigma is only what Model requires.
    accelerometer = [(f"acc_{axis}", "-", f"accelerometer direction a/|a|, sensor {axis}", g)
                     for axis, g in zip("xyz", ca.vertsplit(gravity_direction(q)))]
    m.measurement("imu", accelerometer, sigma=[1.0] * 3)
    bx, bz = m.measurement_params("marg", [("bx", "-", "earth-field reference (20), north component"),
                                           ("bz", "-", "earth-field reference (20), vertical component")])
    magnetometer = [(f"mag_{axis}", "-", f"magnetometer direction m/|m|, sensor {axis}", h)
                    for axis, h in zip("xyz", ca.vertsplit(earth_field_direction(q, ca.vertcat(bx, 0, bz))))]
    m.measurement("marg", accelerometer + magnetometer, sigma=[1.0] * 6)
    m.generic_kernels = ("f", "fd", "jac_fd")
    # what the gradient-descent family needs beyond h(q) vs z (names: codegen/families/gradient_descent.py)
    x, sample, a = ca.SX.sym("x", 4), ca.SX.sym("m", 3), ca.SX.sym("a", 3)
    b = earth_field_reference(x, sample)
    m.functions = {
        "earth_field_reference": ca.Function("marg_earth_field_reference", [x, sample], [ca.vertcat(b[0], b[2])],
                                             ["x", "m"], ["q"], {"cse": True}),
        "initial_orientation": ca.Function("marg_initial_orientation", [a, sample],
                                           [initial_orientation(a, sample)], ["a", "m"], ["x"], {"cse": True}),
    }
    m.filters = ("gradient_descent",)
    return m


__all__ = ["ALPHA_DEFAULT", "BETA_FIG3", "BETA_MADGWICK", "GRAVITY_REFERENCE", "build",
           "earth_field_direction", "earth_field_reference", "euler_angles", "gravity_direction", "gyro_integration",
           "initial_orientation", "objective_components", "objective_earth_field", "objective_general",
           "objective_gradient", "objective_gravity", "objective_stacked", "paper_rotation_matrix",
           "quaternion_rate", "sensor_euler_angles"]

"""Koreasat-3 (A2100 bus) attitude dynamics, sensors and PID law (paper 003).

Park, "Review of back-up possibility on gyro anomaly of geosynchronous satellites using
extended Kalman filter", J. Astron. Space Sci. 22(2), 2005.

- State (17, section 2): integrated attitude angles (the PID integral states), attitude angles
  (psi, phi, theta), body rates omega, wheel momenta h_w1..h_w4, gyro biases b_1..b_4.
- Eq (1): skewed four-gyro geometry (alpha = 54.7 deg, beta = 60 deg), gyros A, B, C, D.
- Eq (2): wheel pyramid (gamma = 45 deg): body torque T = W hdot_wheels, and (same geometry)
  body wheel momentum h_body = W h_wheels.
- Eq (3): rigid body with wheels, -I omegadot = hdot_body + omega x (I omega + h_body), full
  inertia tensor of Table 2 (no external torque).
- Eq (4): omega = M(psi, phi) [psidot, phidot, thetadot]; the model integrates the angles with
  M^-1 omega (M inverted symbolically, never typed by hand).
- Eq (5): PID with feed-forward gain, T_i = K_F (K_P angle + K_I integral + K_D omega), Table 3;
  the commanded body torque goes to the four wheels by the minimum-norm inverse of eq (2).
- Measurements (11): sun sensor (psi), earth sensor (phi, theta), 4 gyros (eq (1) + bias),
  4 wheel tachometers; sigma of Table 5.

Reading of the paper's axes (eq (4)/(5)): psi belongs to x, phi to y, theta to z, and the text
lists them as yaw, roll, pitch. So x is yaw, y roll, z pitch (z has the smallest inertia: the
solar-array / pitch axis). A GEO earth sensor measures roll and pitch and the sun sensor yaw, so
``earth_sensor`` = (phi, theta) at 4 Hz and ``sun_sensor`` = (psi) at 8 Hz.

Units: the paper's own, kept throughout: inertia in-lbf-s^2, momentum in-lbf-s, torque in-lbf,
angles rad, rates rad/s. ``build(units="si")`` builds the same model in kg m^2, N m s and N m
(tests check the motion is unchanged); the PID gains are then converted with the torque factor.
"""
from __future__ import annotations

import casadi as ca
import numpy as np

from .base import Model
from .quaternion import cross_matrix

DEG = np.pi / 180.0
IN_LBF = 0.0254 * 4.4482216152605   # N m per in-lbf (exact by definition of inch and pound-force)

# ---------------------------------------------------------------- Table 2: geometry and inertia
GYRO_ALPHA = 54.7 * DEG            # Table 2, eq (1)
GYRO_BETA = 60.0 * DEG             # Table 2, eq (1)
WHEEL_GAMMA = 45.0 * DEG           # Table 2, eq (2)
INERTIA_IN_LBF_S2 = {              # Table 2, in-lbf-s^2
    "Ixx": 81653.0, "Iyy": 88831.0, "Izz": 17758.0, "Ixy": 53.0, "Ixz": -106.0, "Iyz": 504.0}

# ---------------------------------------------------------------- Table 3: PID gains (x, y, z)
PID_GAINS = {                      # Table 3; torques in in-lbf, angles rad, rates rad/s
    "K_F": (0.5, 0.5, 2.0),
    "K_P": (364.5, 364.5, 52.0),
    "K_I": (2.78125, 2.78125, 0.58984),
    "K_D": (11504.0, 11504.0, 1152.0),
}
CONTROL_RATE_HZ = 2.0              # section 3: attitude control at 2 Hz (zero-order hold)

# ---------------------------------------------------------------- sensor rates (section 3)
EARTH_SENSOR_RATE_HZ = 4.0
SUN_SENSOR_RATE_HZ = 8.0
GYRO_RATE_HZ = 8.0
#: Not given in the paper. Chosen: the tachometers are read once per control cycle (2 Hz), when
#: the control processor reads the wheel speeds to command the wheels.
TACHO_RATE_HZ = 2.0

# ---------------------------------------------------------------- Table 5: sigma, P0, Q, R
SIGMA = {"angle": 1.0e-4, "gyro": 1.0e-6, "tacho": 1.0e-4}           # rad, rad/s, in-lbf-s
P0_TABLE5 = {"angle": 1.0, "rate": 1.0, "tacho": 1.0}
Q_TABLE5 = {"angle": 1.0e-10, "rate": 1.0e-10, "tacho": 1.0e-8}
R_TABLE5 = {"angle": 1.0, "gyro": 1.0e-2, "tacho": 1.0}
#: Not in Table 5 (the gyro row has no P, Q): chosen. Integrated angles take the angle row;
#: the biases take P0 = 1.0 like every other state of Table 5 (a tighter prior, 1e-6 (rad/s)^2,
#: was tried: the bias then needs thousands of seconds to converge), and a tiny Q keeps the
#: (constant) bias nearly constant in the filter.
P0_BIAS = 1.0
Q_BIAS = 1.0e-16

# ---------------------------------------------------------------- Tables 4 and 6: initial errors
#: (angle deg, rate deg/s, wheel momentum in-lbf-s, gyro bias deg/s); x, y, z and wheel/gyro 4.
TABLE4 = {"angle": (-0.03, 0.05, 0.05), "rate": (1.0e-3, -2.0e-3, 2.0e-3),
          "momentum": (-10.0, 5.0, 10.0, -15.0), "bias": (5.0e-5, 1.0e-5, -1.0e-5, -5.0e-5)}
TABLE6 = {"angle": (0.0, 0.0, 0.0), "rate": (0.01, -0.02, 0.02),
          "momentum": (-10.0, 5.0, 10.0, -15.0), "bias": (0.02, -0.01, 0.01, -0.02)}

GYRO_NAMES = ("A", "B", "C", "D")
ANGLE_NAMES = ("psi", "phi", "theta")
STATE_NAMES = (("int_psi", "int_phi", "int_theta") + ANGLE_NAMES + ("omega_x", "omega_y", "omega_z")
               + tuple(f"h_w{i}" for i in range(1, 5)) + tuple(f"b_{i}" for i in range(1, 5)))
SLICES = {"integral": slice(0, 3), "angle": slice(3, 6), "rate": slice(6, 9),
          "momentum": slice(9, 13), "bias": slice(13, 17)}

UNIT_SYSTEMS = {
    # torque factor (model torque unit per in-lbf), unit labels
    "paper": (1.0, {"inertia": "in-lbf-s^2", "momentum": "in-lbf-s", "torque": "in-lbf"}),
    "si": (IN_LBF, {"inertia": "kg m^2", "momentum": "N m s", "torque": "N m"}),
}


# ---------------------------------------------------------------- equations
def gyro_geometry(alpha: float = GYRO_ALPHA, beta: float = GYRO_BETA) -> np.ndarray:
    """Eq (1): [omega_a, omega_b, omega_c, omega_d] = G [omega_x, omega_y, omega_z] (4 x 3)."""
    sa, ca_, sb, cb = np.sin(alpha), np.cos(alpha), np.sin(beta), np.cos(beta)
    return np.array([[0.0, -sa, -ca_],
                     [sb * sa, cb * sa, -ca_],
                     [-sb * sa, cb * sa, -ca_],
                     [0.0, 0.0, 1.0]])


def wheel_pyramid(gamma: float = WHEEL_GAMMA) -> np.ndarray:
    """Eq (2): [T_x, T_y, T_z] = W [hdot_w1..hdot_w4] (3 x 4); also h_body = W h_wheels."""
    s, c = np.sin(gamma), np.cos(gamma)
    return np.array([[s * s, -s * s, -s * s, s * s],
                     [s * c, s * c, -s * c, -s * c],
                     [c, c, c, c]])


def inertia_matrix(units: str = "paper") -> np.ndarray:
    """Table 2 inertia tensor (symmetric, products as printed in eq (3)) in ``units``."""
    i = INERTIA_IN_LBF_S2
    matrix = np.array([[i["Ixx"], i["Ixy"], i["Ixz"]],
                       [i["Ixy"], i["Iyy"], i["Iyz"]],
                       [i["Ixz"], i["Iyz"], i["Izz"]]])
    return matrix * UNIT_SYSTEMS[units][0]


def euler_rate_matrix(psi, phi) -> ca.SX:
    """Eq (4): omega = M(psi, phi) [psidot, phidot, thetadot]."""
    return ca.vertcat(ca.horzcat(1, 0, -ca.sin(phi)),
                      ca.horzcat(0, ca.cos(psi), ca.sin(psi) * ca.cos(phi)),
                      ca.horzcat(0, -ca.sin(psi), ca.cos(psi) * ca.cos(phi)))


def rigid_body_acceleration(omega, h_body, hdot_body, inertia: np.ndarray) -> ca.SX:
    """Eq (3) solved for omegadot: -I omegadot = hdot + omega x (I omega + h)."""
    inertia = ca.DM(inertia)
    rhs = hdot_body + cross_matrix(omega) @ (inertia @ omega + h_body)
    return -ca.DM(np.linalg.inv(np.asarray(inertia))) @ rhs


def pid_torque(integral, angle, rate, units: str = "paper") -> ca.SX:
    """Eq (5): T_i = K_F (K_P angle_i + K_I integral_i + K_D omega_i), Table 3, per axis."""
    torque_factor = UNIT_SYSTEMS[units][0]           # K_P, K_I, K_D carry the torque unit; K_F is a ratio
    g = {k: ca.DM(v) * (1.0 if k == "K_F" else torque_factor) for k, v in PID_GAINS.items()}
    return g["K_F"] * (g["K_P"] * angle + g["K_I"] * integral + g["K_D"] * rate)


def control_law(units: str = "paper") -> ca.Function:
    """Eq (5) then the minimum-norm inverse of eq (2): (integral, angle, rate) -> wheel torques (4)."""
    integral, angle, rate = ca.SX.sym("integral", 3), ca.SX.sym("angle", 3), ca.SX.sym("rate", 3)
    torque = pid_torque(integral, angle, rate, units)
    wheel_torque = ca.DM(np.linalg.pinv(wheel_pyramid())) @ torque
    return ca.Function("geo_control_law", [integral, angle, rate], [wheel_torque, torque],
                       ["integral", "angle", "rate"], ["wheel_torque", "body_torque"])


# ---------------------------------------------------------------- model
def build(units: str = "paper") -> Model:
    """The 17-state model in the paper's units (``units="paper"``) or SI (``"si"``)."""
    if units not in UNIT_SYSTEMS:
        raise ValueError(f"units: expected one of {sorted(UNIT_SYSTEMS)}, got '{units}'")
    torque_factor, label = UNIT_SYSTEMS[units]
    name = "geo_satellite" if units == "paper" else f"geo_satellite_{units}"
    m = Model(name, "Koreasat-3 attitude: PID integral states, Euler angles, rates, pyramid wheels, "
              "skewed gyros with biases", paper="003 (Park 2005, J. Astron. Space Sci. 22(2))")
    for a in ANGLE_NAMES:                                   # d/dt int_a = a, set below
        m.state(f"int_{a}", "rad s", f"time integral of {a} (PID integral state)")
    angle = ca.vertcat(*[m.state(a, "rad", d) for a, d in
                         zip(ANGLE_NAMES, ("yaw angle (x axis)", "roll angle (y axis)", "pitch angle (z axis)"))])
    omega = ca.vertcat(*[m.state(f"omega_{a}", "rad/s", f"body rate about {a}") for a in "xyz"])
    h_wheel = ca.vertcat(*[m.state(f"h_w{i}", label["momentum"], f"momentum of wheel {i}") for i in range(1, 5)])
    bias = ca.vertcat(*[m.state(f"b_{i}", "rad/s", f"bias of gyro {g}") for i, g in enumerate(GYRO_NAMES, 1)])
    hdot_wheel = ca.vertcat(*[m.input(f"hdot_w{i}", label["torque"], f"commanded torque of wheel {i}")
                              for i in range(1, 5)])
    W = ca.DM(wheel_pyramid())
    omegadot = rigid_body_acceleration(omega, W @ h_wheel, W @ hdot_wheel, inertia_matrix(units))
    angle_rate = ca.solve(euler_rate_matrix(angle[0], angle[1]), omega)     # eq (4) inverted
    derivatives = {}
    for i, a in enumerate(ANGLE_NAMES):
        derivatives[f"int_{a}"] = angle[i]
        derivatives[a] = angle_rate[i]
    for i, a in enumerate("xyz"):
        derivatives[f"omega_{a}"] = omegadot[i]
    for i in range(4):
        derivatives[f"h_w{i + 1}"] = hdot_wheel[i]
        derivatives[f"b_{i + 1}"] = ca.SX(0)
    m.set_dynamics(derivatives)

    m.measurement("sun_sensor", [("psi_sun", "rad", "yaw angle from the sun sensor", angle[0])],
                  sigma=[SIGMA["angle"]], wrap=[True])
    m.measurement("earth_sensor", [("phi_earth", "rad", "roll angle from the earth sensor", angle[1]),
                                   ("theta_earth", "rad", "pitch angle from the earth sensor", angle[2])],
                  sigma=[SIGMA["angle"]] * 2, wrap=[True, True])
    gyro_out = ca.DM(gyro_geometry()) @ omega + bias                          # eq (1) + bias
    m.measurement("gyro", [(f"omega_{g}", "rad/s", f"gyro {g} output", gyro_out[i])
                           for i, g in enumerate(GYRO_NAMES)], sigma=[SIGMA["gyro"]] * 4)
    m.measurement("tacho", [(f"h_w{i}_tacho", label["momentum"], f"tachometer of wheel {i}", h_wheel[i - 1])
                            for i in range(1, 5)], sigma=[SIGMA["tacho"] * torque_factor] * 4)
    m.filters = ("cd_ekf",)
    # -O2: measured (bench_geo) to compile ~2x faster than -O3 for the same step time; -O1
    # compiles in 2/3 of the time of -O2 but the predict step is ~30 % slower.
    m.codegen_defaults = {"rk4_substeps": 1, "optimization": "-O2 -fno-math-errno"}
    m.generic_kernels = ("f", "fd", "h")       # the truth and sensors use these; jac_fd is not needed
    return m


def filter_tuning(units: str = "paper") -> dict[str, np.ndarray]:
    """Table 5 as filter matrices: P0 and Q (17 x 17, diagonal) and R per measurement."""
    torque_factor = UNIT_SYSTEMS[units][0]
    p0 = np.r_[[P0_TABLE5["angle"]] * 6, [P0_TABLE5["rate"]] * 3,
               [P0_TABLE5["tacho"] * torque_factor ** 2] * 4, [P0_BIAS] * 4]
    q = np.r_[[Q_TABLE5["angle"]] * 6, [Q_TABLE5["rate"]] * 3,
              [Q_TABLE5["tacho"] * torque_factor ** 2] * 4, [Q_BIAS] * 4]
    return {"P0": np.diag(p0), "Q": np.diag(q),
            "R": {"sun_sensor": np.eye(1) * R_TABLE5["angle"], "earth_sensor": np.eye(2) * R_TABLE5["angle"],
                  "gyro": np.eye(4) * R_TABLE5["gyro"], "tacho": np.eye(4) * R_TABLE5["tacho"] * torque_factor ** 2}}


def initial_errors(table: dict, units: str = "paper", bias: bool = True) -> np.ndarray:
    """A Table 4 / Table 6 row set as a 17-state vector (integral states start at 0)."""
    return np.r_[np.zeros(3), np.asarray(table["angle"]) * DEG, np.asarray(table["rate"]) * DEG,
                 np.asarray(table["momentum"]) * UNIT_SYSTEMS[units][0],
                 np.asarray(table["bias"]) * DEG * (1.0 if bias else 0.0)]

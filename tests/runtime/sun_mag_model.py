"""A user's two-sensor attitude model: a gyro-driven attitude with gyro bias, seen by a sun sensor
and a magnetometer (each a body-frame unit direction), at their own rates in a record.

State: the attitude quaternion (body -> inertial, scalar-last) and the gyro bias b; input: the gyro
rates; q_dot = 1/2 q (x) (omega - b, 0), b constant. Each sensor measures R(q)^T d for a fixed
inertial direction d (SUN, MAG).
"""
import casadi as ca

from symkf.models import Model
from symkf.models import quaternion as quat

SUN = (0.8, 0.6, 0.0)                 # inertial sun direction (unit)
MAG = (0.2, 0.0, 0.9797958971132712)  # inertial magnetic-field direction (unit)


def build():
    m = Model("sun_mag", "gyro-driven attitude with bias, sun sensor and magnetometer", paper="none")
    q = m.quaternion_state("q", "attitude of the body in the inertial frame (body -> inertial)")
    bias = ca.vertcat(*[m.state(f"b_{a}", "rad/s", f"gyro bias, body {a}") for a in "xyz"])
    omega = ca.vertcat(*[m.input(f"w_{a}", "rad/s", f"gyro rate, body {a}") for a in "xyz"])
    m.set_dynamics({"q": 0.5 * quat.hamilton(q, ca.vertcat(omega - bias, 0)),
                    "b_x": 0, "b_y": 0, "b_z": 0})
    to_body = quat.rotation_matrix(q).T
    for name, direction, sigma in (("sun", SUN, 0.01), ("mag", MAG, 0.03)):
        seen = to_body @ ca.DM(direction)
        m.measurement(name, [(f"{name}_{a}", "-", f"{name} direction, body {a}", seen[i]) for i, a in enumerate("xyz")],
                      sigma=[sigma] * 3)
    m.filters = ("mekf", "ekf")
    m.quaternion_as_vector_families = ("ekf",)     # a plain EKF beside the MEKF, on purpose: the run test's second family
    return m

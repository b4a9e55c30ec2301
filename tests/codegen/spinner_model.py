"""A small test model with a quaternion and two ordinary states (the manifold filters' test bench).

A body spins about its z axis at a rate ``w_z`` that decays (time constant TAU) and is measured
by a gyro with bias ``b``; the x/y body rates are known inputs; a body-fixed sensor sees the
gravity direction and a horizontal reference direction (a magnetometer without inclination).
"""
import casadi as ca

from symkf.models import Model
from symkf.models import quaternion as quat

TAU = 20.0


def build():
    m = Model("spinner", "spinning body: attitude quaternion, z rate, z gyro bias", paper="none")
    q = m.quaternion_state("q", "attitude of the body in the inertial frame (body -> inertial)")
    w_z = m.state("w_z", "rad/s", "body z rate")
    b = m.state("b", "rad/s", "z gyro bias")
    wx, wy = m.input("w_x", "rad/s", "body x rate"), m.input("w_y", "rad/s", "body y rate")
    omega = ca.vertcat(wx, wy, w_z)
    m.set_dynamics({"q": 0.5 * quat.hamilton(q, ca.vertcat(omega, 0)), "w_z": -w_z / TAU, "b": 0})
    R_t = quat.rotation_matrix(q).T          # inertial -> body
    g, north = R_t @ ca.DM([0, 0, 1]), R_t @ ca.DM([1, 0, 0])
    m.measurement("vectors", [(f"g_{a}", "-", f"gravity direction, body {a}", g[i]) for i, a in enumerate("xyz")]
                  + [(f"n_{a}", "-", f"north direction, body {a}", north[i]) for i, a in enumerate("xyz")],
                  sigma=[0.02] * 3 + [0.05] * 3)
    m.measurement("gyro_z", [("gz", "rad/s", "z gyro", w_z + b)], sigma=[0.01])
    m.filters = ("mekf", "mukf")
    return m

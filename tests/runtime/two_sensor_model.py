"""A new user's attitude model: a unit quaternion and a gyro bias, propagated with the gyro
sample as input, and two body-frame unit vectors measured (a sun sensor and a magnetometer).

Written the way a user writes a model file; the filter tests take it through every call a
careless user could get wrong (tests/runtime/test_no_silent_answers.py).
"""
import casadi as ca

from symkf.models import Model
from symkf.models import quaternion as quat

SUN = (0.6, 0.0, 0.8)          # the sun direction in the reference frame (unit)
FIELD = (0.0, 0.8, -0.6)       # the magnetic field direction in the reference frame (unit)


def build():
    m = Model("two_sensor", "attitude and gyro bias from a sun sensor and a magnetometer", paper="none")
    q = m.quaternion_state("q", "attitude of the body in the reference frame (body -> reference)")
    b = ca.vertcat(*[m.state(f"b_{a}", "rad/s", f"gyro bias, body {a}") for a in "xyz"])
    gyro = ca.vertcat(*[m.input(f"w_{a}", "rad/s", f"gyro sample, body {a}") for a in "xyz"])
    rate = gyro - b
    m.set_dynamics({"q": 0.5 * quat.hamilton(q, ca.vertcat(rate, 0)), **{f"b_{a}": 0 for a in "xyz"}})
    to_body = quat.rotation_matrix(q).T
    sun, mag = to_body @ ca.DM(SUN), to_body @ ca.DM(FIELD)
    m.measurement("sun", [(f"s_{a}", "-", f"sun direction, body {a}", sun[i]) for i, a in enumerate("xyz")],
                  sigma=[0.01] * 3)
    m.measurement("mag", [(f"m_{a}", "-", f"field direction, body {a}", mag[i]) for i, a in enumerate("xyz")],
                  sigma=[0.03] * 3)
    m.filters = ("mekf", "mukf")
    return m

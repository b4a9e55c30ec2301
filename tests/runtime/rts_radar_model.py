"""A user model for the smoother tests, after FilterPy's UKF RTS test case (filterpy
kalman/tests/test_ukf.py, ``test_rts``): an aircraft at constant altitude seen by a ground radar.

State [downrange position, its velocity, altitude]; FilterPy's f(x) = (I + A dt) x is the Euler
step of dx/dt = A x (``*_integrator = "euler"``); z = slant range sqrt(pos^2 + alt^2). The known
input ``a`` (a downrange acceleration; 0 in FilterPy's case) exercises the smoother's inputs.
"""
import casadi as ca

from symkf.models import Model

RANGE_SIGMA = 10.0 ** 0.5       # m: FilterPy's R = 10 m^2


def build():
    m = Model("rts_radar", "aircraft at constant altitude, ground radar range", paper="none")
    pos = m.state("pos", "m", "downrange position")
    vel = m.state("vel", "m/s", "downrange velocity")
    alt = m.state("alt", "m", "altitude")
    a = m.input("a", "m/s^2", "known downrange acceleration")
    m.set_dynamics({"pos": vel, "vel": a, "alt": 0 * alt})
    m.measurement("range", [("r", "m", "slant range", ca.sqrt(pos**2 + alt**2))], sigma=[RANGE_SIGMA])
    m.filters = ("ekf", "ukf")
    m.codegen_defaults = {"ekf_integrator": "euler", "ukf_integrator": "euler"}
    return m

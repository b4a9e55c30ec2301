"""A user model for the continuous-discrete smoother test: a linear, lightly damped oscillator
with a slow drift, dx/dt = A x (A constant), whose position is measured.

Linear dynamics make the continuous-discrete EKF a Kalman filter whose discrete equivalent is
known in closed form: Phi = expm(A dt) and Q_d = int_0^dt expm(A s) Q expm(A s)^T ds (Van Loan),
so its RTS smoother can be checked against the discrete one with those exact matrices.
"""
from symkf.models import Model

OMEGA, DAMPING, DRIFT = 0.8, 0.05, 0.02     # rad/s, 1/s, 1/s
POSITION_SIGMA = 0.3                          # m


def build():
    m = Model("cd_linear", "damped oscillator with a drifting offset, position measured", paper="none")
    pos = m.state("pos", "m", "position")
    vel = m.state("vel", "m/s", "velocity")
    off = m.state("off", "m", "slowly drifting offset")
    m.set_dynamics({"pos": vel, "vel": -OMEGA ** 2 * (pos - off) - 2 * DAMPING * vel, "off": -DRIFT * off})
    m.measurement("position", [("z", "m", "measured position", pos + off)], sigma=[POSITION_SIGMA])
    m.filters = ("cd_ekf",)
    m.codegen_defaults = {"rk4_substeps": 80}
    return m

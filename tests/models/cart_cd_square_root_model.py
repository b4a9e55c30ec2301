"""A small continuous-discrete model for the square-root CD-EKF's bundle tests: a cart pushed
against a smooth quadratic drag, its position seen as the range from a post beside the track and
its speed by a tachometer (the 17-state geo model of paper 003 is the full-size case, whose strict
builds take minutes: behind the slow marker)."""
import casadi as ca

from symkf.models import Model


def build():
    m = Model("cart_sr", "cart with smooth quadratic drag, range and tachometer", paper="none")
    pos, vel = m.state("pos", "m", "position along the track"), m.state("vel", "m/s", "velocity")
    push = m.input("push", "m/s^2", "commanded acceleration")
    w = m.noise("w", "m/s^2", "acceleration noise")
    m.set_dynamics({"pos": vel, "vel": push - 0.02 * vel * ca.sqrt(vel**2 + 1.0) + w})
    m.measurement("range", [("range", "m", "distance from a post 3 m off the track", ca.sqrt(pos**2 + 9.0))],
                  sigma=[0.1])
    m.measurement("tacho", [("speed", "m/s", "measured velocity", vel)], sigma=[0.05])
    m.filters = ("cd_ekf", "srcdekf")
    return m

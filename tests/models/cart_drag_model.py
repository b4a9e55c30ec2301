"""A cart with linear drag whose drag coefficient the filters estimate (models/estimation.py):
position measured. The truth's drag is 5 % above the model's default (TRUE_DRAG)."""
import casadi as ca

from symkf.models import Model
from symkf.models.estimation import estimate

DRAG = 0.1          # 1/s, the model's value (the estimate's initial value)
TRUE_DRAG = 0.105   # 1/s, the truth's: 5 % more
FORCE = 2.0         # m/s^2, a constant push


def build():
    m = Model("cart_drag", "cart with linear drag, drag estimated", paper="none")
    pos = m.state("pos", "m", "position")
    vel = m.state("vel", "m/s", "velocity")
    drag = m.param("drag", "1/s", "linear drag coefficient", DRAG)
    m.set_dynamics({"pos": vel, "vel": FORCE - drag * vel})
    m.measurement("gps", [("pos", "m", "measured position", pos)], sigma=[0.5])
    estimate(m, "drag", sigma=0.02, random_walk=0.0)
    m.filters = ("ekf", "srukf")
    return m

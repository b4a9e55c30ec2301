"""Design of the launcher guidance (paper 004 gives none): solve it with IPOPT to meet Table 2.

Unknowns: the lift-off flight-path angle (pitch kick), the stage-1 angle-of-attack coefficients,
the stage-2 linear steering law and the stage-2 mass flow (Table 1 is inconsistent there, see
models/launcher.py). Hard constraints: Table 2's altitude and speed at stage-1 separation, and the
insertion conditions r = 6678.137 km, gamma = 0, V = 8.038 km/s at 434.3 s. Objective: the
stage-1 burnout speed and the coast-phase events (fairing jettison, stage-2 ignition altitude and
speed) in least squares. (Burnout speed is soft: with Table 1's stage 1 and any angle-of-attack
program within +-20 deg, 4.68 km/s at 78.8 km is out of reach; the solution lands about 2 % high.) The
trajectory is the truth integrator itself (CVODES with forward sensitivities), so the solved
guidance meets the conditions in the truth exactly.

Run ``symkf design-guidance`` and paste the printed dict into ``models/launcher.py``.
"""
from __future__ import annotations

import casadi as ca
import numpy as np

from symkf.models import launcher as L
from .truth import PHASES, _phase_integrator

UNKNOWNS = ("initial_flight_path_angle",) + L.GUIDANCE_PARAMS
#: The NLP works in degrees, degrees per 100 s and kg/s so that every unknown is of order 1-100.
SCALE = np.array([L.DEG, L.DEG, L.DEG, L.DEG, L.DEG, L.DEG / 100.0, 1.0])
#: gamma_0 at most 86 deg keeps the heading observable from lift-off (see models/launcher.py).
LOWER = [75.0, -20.0, -20.0, -20.0, -20.0, -20.0, 20.0]
UPPER = [86.0, 20.0, 20.0, 20.0, 20.0, 20.0, 60.0]


def _event_states(w: ca.MX) -> list[ca.MX]:
    """States at the end of each phase, symbolic in the unknowns."""
    x = ca.vertcat(L.LIFTOFF_SPEED, w[0], L.LAUNCH_HEADING, L.R_EARTH, L.LAUNCH_LONGITUDE, L.LAUNCH_LATITUDE)
    p = w[1:]
    ends = []
    for phase in range(len(PHASES) - 1):
        x = _phase_integrator(phase, (PHASES[phase + 1],))(x0=x, p=p)["xf"]
        ends.append(x)
    return ends


def solve(initial: dict | None = None) -> dict:
    """Solve the guidance NLP; returns the GUIDANCE dict."""
    w_scaled = ca.MX.sym("w", len(UNKNOWNS))
    burnout, fairing, ignition, insertion = _event_states(w_scaled * SCALE)
    km, kms = 1e3, 1e3
    events = {row[0]: row for row in L.FLIGHT_EVENTS}
    altitude = lambda x: (x[3] - L.R_EARTH) / km   # noqa: E731
    objective = sum(((altitude(x) - events[t][2]) / 5.0) ** 2 + ((x[0] / kms - events[t][3]) / 0.05) ** 2
                    for x, t in ((fairing, L.T_FAIRING), (ignition, L.T_STAGE2_IGNITION)))
    objective += ((burnout[0] / kms - events[L.T_STAGE1_BURNOUT][3]) / 0.02) ** 2
    constraints = ca.vertcat(altitude(burnout) - events[L.T_STAGE1_BURNOUT][2],
                             (insertion[3] - L.INSERTION_RADIUS) / km,
                             insertion[1] - L.INSERTION_FLIGHT_PATH_ANGLE,
                             (insertion[0] - L.INSERTION_SPEED) / kms)
    solver = ca.nlpsol("guidance", "ipopt", {"x": w_scaled, "f": objective, "g": constraints},
                       {"ipopt.print_level": 3, "print_time": False, "ipopt.tol": 1e-9,
                        "ipopt.hessian_approximation": "limited-memory", "ipopt.max_iter": 300})
    start = initial or {**L.GUIDANCE}
    x0 = np.array([start[name] for name in UNKNOWNS]) / SCALE
    result = solver(x0=x0, lbx=LOWER, ubx=UPPER, lbg=0, ubg=0)
    if not solver.stats()["success"]:
        raise RuntimeError(f"guidance NLP did not converge: {solver.stats()['return_status']}")
    return dict(zip(UNKNOWNS, (np.array(result["x"]).ravel() * SCALE).tolist()))


def main() -> int:
    guidance = solve()
    print("GUIDANCE = {")
    for name, value in guidance.items():
        print(f'    "{name}": {value!r},')
    print("}")
    return 0

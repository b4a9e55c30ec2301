"""Truth trajectory of the KSLV-I launcher (paper 004, section 3.1) and its radar data (eq 7).

The truth integrates the *model's own* dynamics ``f`` (models/launcher.py, eq (6)) with CVODES
(adaptive, rtol 1e-11), one integration per flight phase between the model's declared events
(``Model.events``: Table 2's switches), so the thrust, mass and fairing switches fall exactly on
phase boundaries; the filters use fixed-step RK4 at the radar rate, split at the same events
(codegen/discretize.py) — the truth is integrated much finer than the filter step, as the paper's
setup requires. Within a phase the model is evaluated with its time argument held strictly inside
the phase (by EVENT_INSET = 1 microsecond at the ends), which selects the phase's thrust and
mass; nothing is restated.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import casadi as ca
import numpy as np

from symkf.codegen.discretize import EVENT_INSET, continuous_dynamics, measurement_function
from symkf.models import get_model
from symkf.models import launcher as L
from symkf.runtime.reference import wrap_angle

#: Phase boundaries (s): lift-off and the model's events (Table 2).
PHASES = (0.0,) + tuple(get_model("launcher").events)
_INSIDE = EVENT_INSET   # s: how far inside a phase the schedule is evaluated at its ends
TRUTH_TOLERANCES = {"abstol": 1e-9, "reltol": 1e-11, "max_num_steps": 200000}


@lru_cache(maxsize=None)
def _phase_integrator(phase: int, outputs: tuple[float, ...]) -> ca.Function:
    """CVODES over one phase; outputs at the given times (all inside or at the phase end)."""
    model = get_model("launcher")
    f = continuous_dynamics(model)
    t_start, t_end = PHASES[phase], PHASES[phase + 1]
    t_schedule = ca.fmin(ca.fmax(model.t, t_start + _INSIDE), t_end - _INSIDE)
    ode = f(t_schedule, model.x, model.u, model.p, ca.DM.zeros(len(model.noises)))
    dae = {"t": model.t, "x": model.x, "p": model.p, "ode": ode}
    return ca.integrator(f"truth_phase{phase}", "cvodes", dae, t_start, list(outputs), TRUTH_TOLERANCES)


def guidance_vector(guidance: dict | None = None) -> np.ndarray:
    g = L.GUIDANCE if guidance is None else guidance
    return np.array([g[name] for name in L.GUIDANCE_PARAMS])


def propagate(times: np.ndarray, guidance: dict | None = None) -> np.ndarray:
    """True states (len(times), 6) at the given increasing times in [0, 434.3] s."""
    times = np.asarray(times, dtype=float)
    if times.size == 0:
        return np.zeros((0, 6))
    if np.any(np.diff(times) < 0) or times[0] < 0 or times[-1] > PHASES[-1] + 1e-9:
        raise ValueError(f"times must increase within [0, {PHASES[-1]}] s")
    p = guidance_vector(guidance)
    x = L.initial_state(guidance)
    states = np.zeros((times.size, 6))
    states[times <= 0.0] = x
    for phase in range(len(PHASES) - 1):
        t_start, t_end = PHASES[phase], PHASES[phase + 1]
        inside = (times > t_start) & (times <= t_end + 1e-12)
        outputs = tuple(sorted(set(np.round(times[inside], 9).tolist()) | {t_end}))
        result = np.array(_phase_integrator(phase, outputs)(x0=x, p=p)["xf"])
        lookup = dict(zip(outputs, result.T))
        if inside.any():
            states[inside] = [lookup[round(t, 9)] for t in times[inside]]
        x = lookup[t_end]
    return states


@dataclass
class RadarTrack:
    """Radar measurements of a truth trajectory, section 3.2 (hand-over between 3 stations)."""

    times: np.ndarray        # (N,)
    stations: np.ndarray     # (N,) 1, 2 or 3
    clean: np.ndarray        # (N, 3) noise-free range, elevation, azimuth
    measurement: str = "radar"   # the model's measurement: "radar" (spherical) or "radar_wgs84"

    def station_params(self) -> np.ndarray:
        return station_params(self.stations, self.measurement)

    def noisy(self, rng: np.random.Generator) -> np.ndarray:
        """Eq (7): clean values plus sigma times a standard normal draw per component."""
        z = self.clean + rng.standard_normal(self.clean.shape) * np.array(L.RADAR_SIGMA)
        z[:, 2] = wrap_angle(z[:, 2])                    # azimuth back into (-pi, pi]
        return z


def station_params(stations, measurement: str = "radar") -> np.ndarray:
    """(N, nq) parameters of the given stations for the spherical or the WGS84 radar measurement."""
    if measurement not in L.RADAR_MEASUREMENTS.values():
        raise ValueError(f"measurement: expected one of {sorted(L.RADAR_MEASUREMENTS.values())}, got '{measurement}'")
    params = L.station_params if measurement == "radar" else L.station_params_wgs84
    used, index = np.unique(np.asarray(stations, dtype=int), return_inverse=True)
    rows = np.array([params(s) for s in used]).reshape(len(used), -1)    # one row per station,
    return rows[index.reshape(-1)]                                       # copied to every step


def radar_track(times: np.ndarray, states: np.ndarray, measurement: str = "radar") -> RadarTrack:
    """Noise-free radar data from the model's measurement function h (eq 7), spherical
    (``"radar"``, the paper preset) or WGS84 (``"radar_wgs84"``) stations."""
    stations = np.array([L.station_at(t) for t in times])
    params = station_params(stations, measurement)
    h = measurement_function(get_model("launcher"), measurement)
    n = len(times)
    guidance = np.tile(guidance_vector()[:, None], (1, n))
    clean = np.array(h.map(n)(times, states.T, np.zeros((0, n)), guidance, params.T)).T
    return RadarTrack(np.asarray(times, float), stations, clean, measurement)


def events_table(guidance: dict | None = None) -> list[dict]:
    """Table 2 beside the truth: altitude and speed at each event, and the insertion conditions."""
    times = np.array([row[0] for row in L.FLIGHT_EVENTS])
    states = propagate(times, guidance)
    rows = []
    for (t, event, altitude_km, speed_kms), x in zip(L.FLIGHT_EVENTS, states):
        rows.append({"time_s": t, "event": event, "paper_altitude_km": altitude_km,
                     "altitude_km": (x[3] - L.R_EARTH) / 1e3, "paper_speed_kms": speed_kms,
                     "speed_kms": x[0] / 1e3, "flight_path_angle_deg": np.degrees(x[1])})
    return rows

"""Contract cases of a user's LEO orbit-determination model (tests/models/leo_od_model.py: J2,
process noise on the accelerations through m.noise(), a rotating ground station through m.t):
the EKF, UKF and their square-root forms, range / range-rate / azimuth / elevation updates."""
from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np

from symkf.runtime.reference import for_family

from . import Case

MODEL = str(Path(__file__).resolve().parents[1] / "models" / "leo_od_model.py")
DT = 10.0
_TRUTH: dict[int, tuple] = {}


def _module():
    spec = importlib.util.spec_from_file_location("leo_od_model_cases", MODEL)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def cases() -> list[Case]:
    leo = _module()
    x0 = leo.initial_orbit() + np.array([300.0, -200.0, 100.0, 0.3, -0.2, 0.1])
    P0 = np.diag([500.0] * 3 + [0.5] * 3) ** 2
    Q = np.eye(3) * 1e-8
    return [Case(MODEL, family, x0, P0, Q, "tracking", {"kappa": 0.0} if "ukf" in family else {},
                 tolerance=1e-6 if "ukf" in family else 1e-8)
            for family in ("ekf", "ukf", "srekf", "srukf")]


def _truth(k: int):
    """(state, noise-free measurement) at k DT of the true orbit (the model's own f_d and h)."""
    if not _TRUTH:
        leo = _module()
        ref = for_family("ekf")(MODEL, "ekf", leo.initial_orbit(), np.eye(6), np.eye(3))
        x = leo.initial_orbit()
        for j in range(0, 12):
            _TRUTH[j] = (x, ref._h("tracking", j * DT, x, np.zeros(0)))
            x = ref._fd(j * DT, DT, x)
    return _TRUTH[k]


def inputs(case: Case, k: int) -> dict:
    rng = np.random.default_rng(k)
    z = _truth(k)[1] + rng.normal(0.0, [10.0, 0.01, 1e-3, 1e-3])
    return dict(t=(k - 1) * DT, dt=DT, z=z, q=None, u=None)


def reference_states(case: Case, n: int) -> list[np.ndarray]:
    ref = for_family(case.name)(MODEL, case.name, case.x0, case.P0, case.Q, **case.options)
    out = []
    for k in range(1, n + 1):
        a = inputs(case, k)
        ref.step(a["t"], a["dt"], a["z"], case.measurement, np.zeros(0))
        out.append(ref.x.copy())
    return out

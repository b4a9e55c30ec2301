"""Contract cases of the launcher (paper 004): EKF and UKF, radar 1, from t = 10 s."""
from __future__ import annotations

import numpy as np

from symkf.models import launcher as L
from symkf.runtime.reference import ReferenceFilter

from . import Case

MODEL = "launcher"
DT = 0.05
T0 = 10.0
_TRUTH: dict[int, np.ndarray] = {}


def cases() -> list[Case]:
    x0 = L.initial_state() + np.array([5.0, 1e-4, 1e-4, 500.0, 1e-6, 1e-6])
    P0 = np.diag([10.0, 1e-3, 1e-3, 1e3, 1e-5, 1e-5]) ** 2
    Q = np.diag([1.0, 1e-8, 1e-8, 1.0, 1e-14, 1e-14])
    tags = frozenset({"separate_update"})
    return [Case(MODEL, "ekf", x0, P0, Q, "radar", t0=T0, tags=tags),
            Case(MODEL, "ukf", x0, P0, Q, "radar", {"kappa": 0.0}, t0=T0, tags=tags, tolerance=1e-6)]


def radar(k: int) -> np.ndarray:
    """Radar 1's noise-free measurement of the launcher's state at T0 + DT k (the model's f_d, h)."""
    if not _TRUTH:
        ref = ReferenceFilter(MODEL, "ekf", L.initial_state(), np.eye(6), np.eye(6))
        truth = [L.initial_state()]
        for j in range(1, 40):
            truth.append(ref._fd(T0 + DT * (j - 1), DT, truth[-1]))
        _TRUTH.update({j: ref._h("radar", T0 + DT * j, x, L.station_params(1)) for j, x in enumerate(truth)})
    return _TRUTH[k]


def inputs(case: Case, k: int) -> dict:
    rng = np.random.default_rng(k)
    return dict(t=T0 + (k - 1) * DT, dt=DT, z=radar(k) + rng.normal(0, [10, 1e-4, 1e-4]), q=L.station_params(1), u=None)


def reference_states(case: Case, n: int) -> list[np.ndarray]:
    ref = ReferenceFilter(MODEL, case.name, case.x0, case.P0, case.Q, **case.options)
    out = []
    for k in range(1, n + 1):
        a = inputs(case, k)
        ref.step(a["t"], a["dt"], a["z"], case.measurement, a["q"])
        out.append(ref.x.copy())
    return out

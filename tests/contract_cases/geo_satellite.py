"""Contract cases of the Koreasat-3 model (paper 003): the continuous-discrete EKF, gyro update; the
square-root CD-EKF on the same model with that family added (tests/models/geo_square_root_model.py)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from symkf.models import geo_satellite as G
from symkf.models import get_model
from symkf.runtime.reference import for_family

from . import Case

MODEL = "geo_satellite"
SQUARE_ROOT_MODEL = str(Path(__file__).resolve().parents[1] / "models" / "geo_square_root_model.py")
DT = 0.125


def cases() -> list[Case]:
    tune = G.filter_tuning()
    x0 = G.initial_errors(G.TABLE6) + np.r_[np.zeros(3), 1e-3 * np.ones(3), np.zeros(11)]
    return [Case(model, family, x0, tune["P0"], tune["Q"], "gyro", {"R": tune["R"]}, tags=frozenset({"separate_update"}))
            for model, family in ((MODEL, "cd_ekf"), (SQUARE_ROOT_MODEL, "srcdekf"))]


def inputs(case: Case, k: int) -> dict:
    rng = np.random.default_rng(k)
    return dict(t=(k - 1) * DT, dt=DT, z=1e-4 * rng.standard_normal(4), q=None, u=np.array([0.3, -0.1, 0.2, 0.05]))


def reference_states(case: Case, n: int) -> list[np.ndarray]:
    ref = for_family(case.name)(get_model(case.model), case.x0, case.P0, case.Q, case.options["R"])
    out = []
    for k in range(1, n + 1):
        a = inputs(case, k)
        ref.predict(a["t"], a["dt"], u=a["u"])
        ref.update(a["z"], measurement=case.measurement)
        out.append(ref.x.copy())
    return out

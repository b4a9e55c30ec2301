"""Contract cases of the MARG model (paper 001): the gradient-descent filter, simple and full
forms, accelerometer-only ("imu") and accelerometer + magnetometer ("marg") samples."""
from __future__ import annotations

import numpy as np

from symkf.runtime.reference.gradient_descent import ReferenceGradientDescent

from . import Case

MODEL = "marg"
DT = 0.01


def cases() -> list[Case]:
    q0 = np.array([0.0, 0.0, np.sin(0.1), np.cos(0.1)])
    return [Case(MODEL, f"gd_{form}", q0, measurement=mode, options={"p": [0.1, 2.0]},
                 tags=frozenset({"gradient_descent"}))
            for form in ("simple", "full") for mode in ("imu", "marg")]


def inputs(case: Case, k: int) -> dict:
    rng = np.random.default_rng(k)
    acc = np.array([0.1, -0.2, 9.8]) + 0.05 * rng.standard_normal(3)
    mag = np.array([20.0, 1.0, -40.0]) + rng.standard_normal(3)
    return dict(t=(k - 1) * DT, dt=DT, z=acc if case.measurement == "imu" else np.r_[acc, mag], q=None,
                u=np.array([0.01, -0.02, 0.3]))


def reference_states(case: Case, n: int) -> list[np.ndarray]:
    ref = ReferenceGradientDescent(MODEL, case.name, case.x0, case.options["p"])
    out = []
    for k in range(1, n + 1):
        a = inputs(case, k)
        out.append(ref.step(a["t"], a["dt"], a["z"], case.measurement, u=a["u"]).copy())
    return out

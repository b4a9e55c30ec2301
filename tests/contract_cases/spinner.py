"""Contract cases of a user model file with a quaternion state (tests/codegen/spinner_model.py):
the generated manifold MEKF and UKF, two body-frame vectors measured."""
from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from symkf.runtime.reference import ManifoldReference

from . import Case

MODEL = str(Path(__file__).resolve().parents[1] / "codegen" / "spinner_model.py")
DT = 0.02


def cases() -> list[Case]:
    q0 = np.array([0.1, -0.2, 0.3, 0.9]) / np.linalg.norm([0.1, -0.2, 0.3, 0.9])
    sigma = np.sqrt([0.02, 0.03, 0.05, 0.01, 1e-4])
    P0 = np.outer(sigma, sigma) * (0.8 * np.eye(5) + 0.2)
    Q = np.diag([1e-4, 1e-4, 2e-4, 1e-3, 1e-6])
    return [Case(MODEL, "mekf", np.r_[q0, 0.4, 0.02], P0, Q, "vectors"),
            Case(MODEL, "mukf", np.r_[q0, 0.4, 0.02], P0, Q, "vectors", {"kappa": 0.5})]


def inputs(case: Case, k: int) -> dict:
    rng = np.random.default_rng(k)
    R_t = Rotation.from_quat(case.x0[:4]).as_matrix().T
    return dict(t=(k - 1) * DT, dt=DT, z=np.r_[R_t @ [0, 0, 1.0], R_t @ [1.0, 0, 0]] + rng.normal(0, 0.01, 6),
                q=None, u=np.array([0.3, -0.2]))


def reference_states(case: Case, n: int) -> list[np.ndarray]:
    ref = ManifoldReference(MODEL, case.name, case.x0, case.P0, case.Q, kappa=case.options.get("kappa", 0.0))
    out = []
    for k in range(1, n + 1):
        a = inputs(case, k)
        ref.step(a["t"], a["dt"], a["z"], case.measurement, u=a["u"])
        out.append(ref.x.copy())
    return out

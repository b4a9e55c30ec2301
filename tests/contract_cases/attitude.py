"""Contract cases of the star-tracker/gyro attitude model (paper 000): MEKF, separated and
augmented UKF with the quaternion mean, star-tracker update (z a unit quaternion); the square-root
MEKF on the same model with that family added (tests/models/attitude_square_root_model.py), held
to the paper's MEKF reference (the same estimator)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from symkf.models import attitude as A
from symkf.scenarios.attitude.filter import ReferenceAttitudeFilter

from . import Case

MODEL = "attitude"
SQUARE_ROOT_MODEL = str(Path(__file__).resolve().parents[1] / "models" / "attitude_square_root_model.py")
DT = 0.25


def cases() -> list[Case]:
    q0 = np.array([0.1, -0.2, 0.3, 0.9])
    x0 = np.r_[q0 / np.linalg.norm(q0), 1e-5, -2e-5, 1e-5]
    P0 = np.diag([1e-4] * 3 + [1e-10] * 3)
    Q = A.process_noise_psd()
    R = {"star_tracker": A.star_tracker_covariance()}
    # z is perturbed by ~2 mrad against sigma 0.4 mrad: a stress record, not a consistent one, so the
    # default gate would refuse some updates; the references have no gate
    options = {"R": R, "gate": {"star_tracker": None}}
    return [Case(SQUARE_ROOT_MODEL if kind == "srmekf" else MODEL, kind, x0, P0, Q, "star_tracker",
                 dict(options, **({"kappa": 1.0} if "ukf" in kind else {})),
                 tags=frozenset({"quaternion_z"}), runs_by_steps=True, mask_size=1)   # Q/dt: every dt > 0
            for kind in ("mekf", "sukf", "aukf", "srmekf")]


def inputs(case: Case, k: int) -> dict:
    rng = np.random.default_rng(k)
    q_s = case.x0[:4] + 1e-3 * rng.standard_normal(4)
    return dict(t=(k - 1) * DT, dt=DT, z=q_s / np.linalg.norm(q_s), q=None, u=np.array([1e-3, -2e-3, 5e-4]))


def reference_states(case: Case, n: int) -> list[np.ndarray]:
    kind = {"sukf": "ukf", "srmekf": "mekf"}.get(case.name, case.name)     # the paper's names
    ref = ReferenceAttitudeFilter(kind, case.x0[:4], case.x0[4:], case.P0, case.Q, case.options["R"]["star_tracker"],
                                  kappa=case.options.get("kappa", 1.0))
    out = []
    for k in range(1, n + 1):
        a = inputs(case, k)
        ref.step(a["u"], a["dt"], a["z"])
        out.append(ref.x.copy())
    return out

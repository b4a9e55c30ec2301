"""Paper 000's efficiency claim: sigma points and µs per step of the MEKF, the paper's separated-space
UKF ([x, w] and [x, v]) and the full augmented UKF ([x, w, v]).

    symkf bench attitude [--json] [--steps N] [--repeats R]

For each filter: compiled step (one C call from Python per step), compiled run (the time loop in
C, µs per step), and the NumPy reference (plain Python). Steps are timed both as propagation only
(gyro, no star tracker) and as propagation + star-tracker update. Medians over ``--repeats``.
"""
from __future__ import annotations

import json
import time

import numpy as np
from scipy.spatial.transform import Rotation

from ..codegen.families import attitude as family
from ..runtime import load
from ..runtime.attitude import AttitudeFilter, ReferenceAttitudeFilter

KINDS = ("mekf", "ukf", "aukf")
SIGMA_POINTS = {
    "mekf": {"propagation": 0, "update": 0, "cholesky": "none (3x3 solve of S)"},
    "ukf": {"propagation": family.N_PROPAGATION_POINTS, "update": family.N_UPDATE_POINTS,
            "cholesky": "6x6 P + 6x6 Q (propagation), 6x6 P + 3x3 R + 3x3 P^yy (update)"},
    "aukf": {"propagation": family.N_AUGMENTED_POINTS, "update": family.N_AUGMENTED_POINTS,
             "cholesky": "15x15 blockdiag(P, Q, R) + 3x3 P^yy, once per step"},
}


def _inputs(n_steps: int, with_star: bool, seed: int = 1):
    rng = np.random.default_rng(seed)
    truth = Rotation.random(random_state=seed)
    omega = rng.normal(scale=0.01, size=(n_steps, 3))
    stars = truth * Rotation.from_rotvec(rng.normal(scale=1e-3, size=(n_steps, 3)))
    z = stars.as_quat() if with_star else np.full((n_steps, 4), np.nan)
    return truth.as_quat(), omega, z


def _median_us(function, repeats: int, steps: int) -> float:
    samples = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        samples.append((time.perf_counter() - start) / steps * 1e6)
    return float(np.median(samples))


def bench(steps: int, repeats: int, reference_steps: int) -> dict:
    compiled = load("attitude", backend="compiled")
    P0 = np.diag([1e-6] * 3 + [1e-12] * 3)      # stays far from |δp| = 1 over a propagation-only record
    results = {}
    for kind in KINDS:
        row = {"sigma_points": SIGMA_POINTS[kind]}
        for label, with_star in (("propagate", False), ("propagate_update", True)):
            q0, omega, z = _inputs(steps, with_star)
            stars = [None if not with_star else zi for zi in z]

            def step_loop():
                filt = AttitudeFilter(compiled, kind, q0, np.zeros(3), P0)
                for w, zi in zip(omega, stars):
                    filt.step(w, 0.25, zi)

            def run_loop():
                AttitudeFilter(compiled, kind, q0, np.zeros(3), P0).run(omega, 0.25, z)

            def reference_loop():
                filt = ReferenceAttitudeFilter(kind, q0, np.zeros(3), P0)
                for w, zi in zip(omega[:reference_steps], stars[:reference_steps]):
                    filt.step(w, 0.25, zi)

            row[label] = {"compiled_step_us": _median_us(step_loop, repeats, steps),
                          "compiled_run_us": _median_us(run_loop, repeats, steps),
                          "numpy_reference_us": _median_us(reference_loop, max(1, repeats // 3), reference_steps)}
        results[kind] = row
    for label in ("propagate", "propagate_update"):
        ukf, aukf = results["ukf"][label]["compiled_run_us"], results["aukf"][label]["compiled_run_us"]
        results.setdefault("ratios", {})[f"augmented_over_separated_{label}"] = aukf / ukf
        results["ratios"][f"ukf_over_mekf_{label}"] = ukf / results["mekf"][label]["compiled_run_us"]
    return results


def add_arguments(parser) -> None:
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    parser.add_argument("--steps", type=int, default=2000, help="steps per timing (default 2000)")
    parser.add_argument("--repeats", type=int, default=7, help="repeats, median reported (default 7)")
    parser.add_argument("--reference-steps", type=int, default=40, help="steps timed for the NumPy reference")


def run(args) -> int:
    results = bench(args.steps, args.repeats, args.reference_steps)
    if args.json:
        print(json.dumps(results, indent=1))
        return 0
    print("paper 000 attitude filters, µs per step (median)")
    print(f"{'filter':<6} {'sigma pts (prop/upd)':>21} {'step':>8} {'':<18} {'C step':>9} {'C run':>9} {'NumPy':>10}")
    for kind in KINDS:
        sp = results[kind]["sigma_points"]
        for label in ("propagate", "propagate_update"):
            r = results[kind][label]
            print(f"{kind:<6} {sp['propagation']:>10}/{sp['update']:<10} {label:>26} {r['compiled_step_us']:>9.2f} "
                  f"{r['compiled_run_us']:>9.2f} {r['numpy_reference_us']:>10.0f}")
    for name, value in results["ratios"].items():
        print(f"{name}: {value:.2f}")
    return 0

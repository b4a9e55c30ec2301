"""Paper 000's efficiency claim: sigma points and µs per step of the MEKF, the paper's separated-space
UKF ([x, w] and [x, v]) and the full augmented UKF ([x, w, v]).

    symkf bench attitude [--json] [--steps N] [--repeats R]

For each filter: the predict kernel and the step kernel (propagation + star-tracker update) as
one bound C call each, the C run loop (µs per step, update every step), the Python filter
object's step (propagation only / with update), and the NumPy reference (plain Python).
Every path of a filter is timed in each of ``--repeats`` interleaved rounds (the same machine
load for all); medians of wall time, and of the timing thread's CPU time (``cpu_us``). The load
average is printed beside them: read ratios, not digits.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from symkf.models import get_model
from symkf.runtime import load
from symkf.scenarios import timing
from symkf.scenarios.report import emit
from symkf.scenarios.attitude.filter import AttitudeFilter
from symkf.scenarios.attitude.reference import ReferenceAttitudeFilter

KINDS = ("mekf", "ukf", "aukf")


def sigma_point_counts(model_name: str = "attitude") -> dict[str, int]:
    """Sigma points of the separated ([x, w], [x, v]) and augmented ([x, w, v]) UKFs of a model:
    2 n + 1 with n the error-state plus noise dimensions (25, 19 and 31 for paper 000)."""
    model = get_model(model_name)
    n_e, n_w = model.n_error, len(model.noises)
    n_v = max(m.v.shape[0] for m in model.measurements.values())
    return {"propagation": 2 * (n_e + n_w) + 1, "update": 2 * (n_e + n_v) + 1, "augmented": 2 * (n_e + n_w + n_v) + 1}


_COUNTS = sigma_point_counts()
SIGMA_POINTS = {
    "mekf": {"propagation": 0, "update": 0, "cholesky": "none (3x3 solve of S)"},
    "ukf": {"propagation": _COUNTS["propagation"], "update": _COUNTS["update"],
            "cholesky": "6x6 P + 6x6 Q (propagation), 6x6 P + 3x3 R + 3x3 P^yy (update)"},
    "aukf": {"propagation": _COUNTS["augmented"], "update": _COUNTS["augmented"],
             "cholesky": "15x15 blockdiag(P, Q, R) + 3x3 P^yy, once per step"},
}


def _inputs(n_steps: int, with_star: bool, seed: int = 1):
    rng = np.random.default_rng(seed)
    truth = Rotation.random(random_state=seed)
    omega = rng.normal(scale=0.01, size=(n_steps, 3))
    stars = truth * Rotation.from_rotvec(rng.normal(scale=1e-3, size=(n_steps, 3)))
    z = stars.as_quat() if with_star else np.full((n_steps, 4), np.nan)
    return truth.as_quat(), omega, z


def _kernel_loop(filt: AttitudeFilter, call, calls: int):
    """``calls`` bound kernel calls (x, P restored after each, so every call does the same work)."""
    x0, P0 = filt.x.copy(), filt.P.copy()
    x, P = filt.kernel_buffer("x"), filt.kernel_buffer("P")

    def loop(i):
        for _ in range(calls):
            call()
            x[:] = x0
            P[:] = P0
    return loop


def bench(steps: int, repeats: int, reference_steps: int) -> dict:
    """Every path of a filter in ``repeats`` interleaved rounds (each round times each path once,
    in turn, so that all see the same machine load): medians of wall and thread CPU µs per step."""
    compiled = load("attitude", backend="compiled")
    P0 = np.diag([1e-6] * 3 + [1e-12] * 3)      # stays far from |δp| = 1 over a propagation-only record
    results = {"load_average": {"before": timing.load_average()}}
    for kind in KINDS:
        q0, omega, z = _inputs(steps, True)
        filt = AttitudeFilter(compiled, kind, q0, np.zeros(3), P0)
        x, P = filt.x.copy(), filt.P.copy()
        filt.step(omega[0], 0.25, z[0])                 # fills the input buffers of the bound kernels
        filt.x, filt.P = x, P
        paths = {"kernel_predict_us": _kernel_loop(filt, filt.kernel_call("predict"), steps),
                 "kernel_step_with_update_us": _kernel_loop(filt, filt.kernel_call("step"), steps),
                 "run_loop_step_with_update_us":
                     lambda i: AttitudeFilter(compiled, kind, q0, np.zeros(3), P0).run(omega, 0.25, z)}
        calls = dict.fromkeys(paths, steps)
        for label, with_star in (("propagate", False), ("propagate_update", True)):
            stars = [zi if with_star else None for zi in z]

            def step_loop(i, stars=stars):
                f = AttitudeFilter(compiled, kind, q0, np.zeros(3), P0)
                for w, zi in zip(omega, stars):
                    f.step(w, 0.25, zi)

            def reference_loop(i, stars=stars):
                f = ReferenceAttitudeFilter(kind, q0, np.zeros(3), P0)
                for w, zi in zip(omega[:reference_steps], stars[:reference_steps]):
                    f.step(w, 0.25, zi)

            paths[f"python_filter_step_{label}_us"], calls[f"python_filter_step_{label}_us"] = step_loop, steps
            paths[f"numpy_reference_{label}_us"], calls[f"numpy_reference_{label}_us"] = reference_loop, reference_steps
        samples = timing.interleaved(paths, repeats, calls)
        results[kind] = {"sigma_points": SIGMA_POINTS[kind], **{path: s.us for path, s in samples.items()},
                         "cpu_us": {path: s.cpu_us for path, s in samples.items()}}
    results["load_average"]["after"] = timing.load_average()
    results["ratios"] = {
        "augmented_over_separated_predict": results["aukf"]["kernel_predict_us"] / results["ukf"]["kernel_predict_us"],
        "augmented_over_separated_step": results["aukf"]["kernel_step_with_update_us"]
        / results["ukf"]["kernel_step_with_update_us"],
        "ukf_over_mekf_step": results["ukf"]["kernel_step_with_update_us"]
        / results["mekf"]["kernel_step_with_update_us"],
        "numpy_over_compiled_ukf_step": results["ukf"]["numpy_reference_propagate_update_us"]
        / results["ukf"]["kernel_step_with_update_us"],
    }
    return results


def add_arguments(parser) -> None:
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    parser.add_argument("--steps", type=int, default=2000, help="steps per timing (default 2000)")
    parser.add_argument("--repeats", type=int, default=7, help="repeats, median reported (default 7)")
    parser.add_argument("--reference-steps", type=int, default=40, help="steps timed for the NumPy reference")


def run(args) -> int:
    results = bench(args.steps, args.repeats, args.reference_steps)
    emit(results, None, args.json, _print)
    return 0


def _print(results: dict) -> None:
    load = results["load_average"]
    print("paper 000 attitude filters, µs per step (median of interleaved rounds); kernel = one bound C call, "
          f"run = C time loop; cpu = the thread's CPU time; load average {load['before'][0]:.2f} before, {load['after'][0]:.2f} after")
    print(f"{'filter':<6} {'sigma pts prop/upd':>18} {'predict':>9} {'step+upd':>9} {'run/step':>9} "
          f"{'py step':>9} {'py step+upd':>11} {'NumPy':>9} {'NumPy+upd':>10}")
    for kind in KINDS:
        sp = results[kind]["sigma_points"]
        for label, r in ((kind, results[kind]), ("  cpu", results[kind]["cpu_us"])):
            points = f"{sp['propagation']:>9}/{sp['update']:<8}" if label == kind else f"{'':>18}"
            print(f"{label:<6} {points} {r['kernel_predict_us']:>9.2f} "
                  f"{r['kernel_step_with_update_us']:>9.2f} {r['run_loop_step_with_update_us']:>9.2f} "
                  f"{r['python_filter_step_propagate_us']:>9.2f} {r['python_filter_step_propagate_update_us']:>11.2f} "
                  f"{r['numpy_reference_propagate_us']:>9.0f} {r['numpy_reference_propagate_update_us']:>10.0f}")
    for name, value in results["ratios"].items():
        print(f"{name}: {value:.2f}")

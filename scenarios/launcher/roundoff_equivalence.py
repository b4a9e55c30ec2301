"""Does a build that changes only round-off give the campaign's answers? (Table 3 of paper 004)

Compares a build whose numbers differ from the scalar code's by round-off (``BUILDS``: the
UKF's sigma points in SIMD lanes, ``ukf_lanes``; or the campaign's own build, runs in lockstep
with libmvec's sin, cos, exp, atan2, ``<family>_lockstep_vector_math``) with the reference build
(``REFERENCE_BUILD``: the scalar code of every sigma point, each run alone, as the flight bundle
computes), run by run on the campaign's draws, as the campaign runs them (``Filter.run_lockstep``
and ``smooth_lockstep`` in groups of ``LOCKSTEP_RUNS``; a build without lockstep loops runs each
run alone):

- per run and state, whole-flight RMS sqrt(mean_t e^2), over the runs neither build classes as an
  excursion or divergence (``campaign.outcome``): the largest relative difference (criterion: 1e-6),
  with that run's difference in units in the last place of the state itself (a smoother's
  latitude error is about 1e-9 rad on a latitude of 2.2 rad: 1e-6 of it is 2 ulp of the latitude);
- each Table 3 cell (eq (11): mean over time of the RMS over runs, angles in degrees) of both
  builds, and the reference cell's Monte Carlo standard error (bootstrap over runs); criterion:
  |new - reference| <= 2 standard errors;
- the runs whose class (ok / excursion / diverged) differs: allowed only where either build
  classes the run as an excursion.

    python -m symkf.scenarios.launcher.roundoff_equivalence [--build lockstep-vector-math]
        [--preset correct] [--runs 100] [--bootstrap 200]
"""
from __future__ import annotations

import argparse
import sys

import numpy as np

from symkf.models import launcher as L
from symkf.runtime import smooth_lockstep
from symkf.scenarios.metrics import state_error
from .campaign import (ANGLE_STATES, LOCKSTEP_BUILD, LOCKSTEP_RUNS, PRESETS, STATE_NAMES, Case, case_flight,
                       chunks_of, initial_estimate, make_filter, measurements, outcome)

#: The build whose numbers the comparison starts from: the scalar code of every sigma point, one run at a time.
REFERENCE_BUILD = {"ukf_lanes": False, "ukf_centre_free": False}
#: The builds compared with it (the library's default is the scalar code).
BUILDS = {"lanes": {"ukf_lanes": True}, "lockstep-vector-math": LOCKSTEP_BUILD}
FAMILIES = ("ekf", "ukf")
SEED = 2005


def run_errors(model, case: Case, runs: int, family: str, tuning: dict) -> dict[str, np.ndarray]:
    """{estimate: (runs, steps, 6) errors truth - estimate} of a filter and its smoothing over the
    case's first ``runs`` runs, as ``campaign.run_chunk`` makes them (the same draws, tuning,
    initial estimate, filter and loops)."""
    measurement = L.RADAR_MEASUREMENTS[tuning["stations"]]
    times, truth, track = case_flight(case.rate_hz, L.T_INSERTION, measurement)
    q, (x0, P0) = track.station_params(), initial_estimate(case, truth[0], tuning["P0_floor"])
    f = make_filter(model, family, x0, P0, tuning, times[0])
    out = {estimate: np.empty((runs, len(times), 6)) for estimate in (family, f"{family}_rts")}
    for group in chunks_of(range(runs), LOCKSTEP_RUNS):
        z = np.stack([measurements(SEED, case, run, track) for run in group])
        results = f.run_lockstep(times, z, measurement, q=q)
        smoothings = smooth_lockstep(f, results, errors="keep")
        for run, result, smoothed in zip(group, results, smoothings):
            out[family][run] = state_error(truth, result.x, ANGLE_STATES)
            out[f"{family}_rts"][run] = state_error(truth, smoothed.x_smooth, ANGLE_STATES)
    return out


def table_cell(squared: np.ndarray) -> np.ndarray:
    """Eq (11) per state in Table 3's units from (runs, steps, 6) squared errors: mean over time of
    sqrt(mean over runs of e^2)."""
    rms = np.sqrt(np.mean(squared, axis=0))
    return np.where(ANGLE_STATES, np.degrees(rms), rms).mean(axis=0)


def bootstrap_se(squared: np.ndarray, draws: int, rng: np.random.Generator) -> np.ndarray:
    """The Monte Carlo standard error of each cell: its spread over runs drawn with replacement."""
    cells = [table_cell(squared[rng.integers(0, len(squared), len(squared))]) for _ in range(draws)]
    return np.std(cells, axis=0, ddof=1)


def compare_estimate(case: Case, estimate: str, e_new: np.ndarray, e_ref: np.ndarray, draws: int,
                     state_ulp: np.ndarray) -> dict:
    """One estimate's comparison on one case (see the module docstring) from both builds' errors;
    ``state_ulp``: each state's spacing at its largest |truth| over the flight."""
    kinds = [(outcome(a), outcome(b)) for a, b in zip(e_new, e_ref)]
    ok = np.array([a == "ok" and b == "ok" for a, b in kinds])
    rms_new, rms_ref = np.sqrt(np.mean(e_new**2, axis=1)), np.sqrt(np.mean(e_ref**2, axis=1))
    relative = np.abs(rms_new - rms_ref) / np.abs(rms_ref)
    ulps = np.abs(rms_new - rms_ref) / state_ulp
    cell_new, cell_ref = table_cell(e_new**2), table_cell(e_ref**2)
    se = bootstrap_se(e_ref**2, draws, np.random.default_rng(7))
    changed = [(run, a, b) for run, (a, b) in enumerate(kinds) if a != b]
    worst = np.unravel_index(np.argmax(np.where(ok[:, None], relative, -1.0)), relative.shape)
    return {"case": case.label, "estimate": estimate, "ok_runs": int(ok.sum()),
            "max_rel_rms_ok": float(relative[ok].max()) if ok.any() else 0.0,
            "over_1e-6": int(np.count_nonzero(ok[:, None] & (relative > 1e-6))),
            "worst": (int(worst[0]), STATE_NAMES[worst[1]], float(rms_ref[worst]),
                      float(rms_new[worst] - rms_ref[worst]), float(ulps[worst])),
            "bitwise_equal_runs": int(sum(np.array_equal(a, b) for a, b in zip(e_new, e_ref))),
            "cell_new": cell_new, "cell_ref": cell_ref, "se": se, "within_2se": bool(np.all(np.abs(cell_new - cell_ref)
                                                                                          <= 2 * se)),
            "class_changes": changed, "class_changes_allowed": all("excursion" in (a, b) for _, a, b in changed)}


def report_lines(rows: list[dict]) -> list[str]:
    lines = []
    for r in rows:
        lines.append(f"{r['case']:<11} {r['estimate']:<7} ok runs {r['ok_runs']:>3}, bit-equal runs "
                     f"{r['bitwise_equal_runs']:>3}, max rel. diff of per-run RMS (ok runs) {r['max_rel_rms_ok']:.2e} "
                     "(run {}, {}: RMS {:.4g}, diff {:+.2e}, {:.0f} ulp of the state), ".format(*r["worst"]) +
                     f"{r['over_1e-6']} (run, state) over 1e-6, " +
                     f"class changes {r['class_changes'] or 'none'}{'' if r['class_changes_allowed'] else ' (NOT ALLOWED)'}")
        for name, a, b, s in zip(STATE_NAMES, r["cell_new"], r["cell_ref"], r["se"]):
            flag = "" if abs(a - b) <= 2 * s else "   > 2 SE"
            lines.append(f"    {name:<6} new {a:.6g}  reference {b:.6g}  diff {a - b:+.3e}  SE {s:.3e}  "
                         f"|diff|/SE {abs(a - b) / s if s else 0.0:.3f}{flag}")
    return lines


def main(argv=None) -> int:
    from symkf.runtime import load
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--build", choices=sorted(BUILDS), default="lockstep-vector-math")
    parser.add_argument("--preset", choices=sorted(PRESETS), default="correct")
    parser.add_argument("--runs", type=int, default=100)
    parser.add_argument("--bootstrap", type=int, default=200)
    parser.add_argument("--families", default=",".join(FAMILIES))
    args = parser.parse_args(argv)
    preset = PRESETS[args.preset]
    new = load("launcher", backend="compiled", **{**BUILDS[args.build], **preset["codegen"]})
    reference = load("launcher", backend="compiled", **{**REFERENCE_BUILD, **preset["codegen"]})
    rows = []
    for case in [Case(rate, init) for rate in L.RADAR_RATES_HZ for init in ("small", "large")]:
        truth = case_flight(case.rate_hz, L.T_INSERTION, L.RADAR_MEASUREMENTS[preset["tuning"]["stations"]])[1]
        state_ulp = np.spacing(np.max(np.abs(truth), axis=0))
        for family in args.families.split(","):
            e_new, e_ref = (run_errors(m, case, args.runs, family, preset["tuning"]) for m in (new, reference))
            for estimate in e_new:
                rows.append(compare_estimate(case, estimate, e_new[estimate], e_ref[estimate], args.bootstrap,
                                             state_ulp))
                print("\n".join(report_lines(rows[-1:])), flush=True)
    return 0 if verdict_lines(rows) else 1


def verdict_lines(rows: list[dict]) -> bool:
    """Prints each estimate's verdict on the criterion; True if it holds for every estimate."""
    verdicts = {}
    for r in rows:
        verdicts.setdefault(r["estimate"], []).append(r["within_2se"] and r["class_changes_allowed"]
                                                      and r["max_rel_rms_ok"] <= 1e-6)
    for estimate, met in verdicts.items():
        print(f"{estimate}: criterion met in {sum(met)} of {len(met)} cases{'' if all(met) else ': NOT met'}")
    return all(all(met) for met in verdicts.values())


if __name__ == "__main__":
    sys.exit(main())

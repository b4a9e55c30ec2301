"""Does a build that changes only round-off give the campaign's answers? (Table 3 of paper 004)

Compares the build with ``ukf_lanes=True`` (the UKF's sigma points in SIMD lanes, libmvec's
sin/cos; the centre point skipped at kappa = 0) with a reference build (``REFERENCE_BUILD``: every point propagated by
the scalar code, as the flight bundle does), run by run on the default campaign's draws:

- per run and state, whole-flight RMS sqrt(mean_t e^2), over the runs neither build classes as an
  excursion or divergence (``campaign.outcome``): the largest relative difference (criterion: 1e-6);
- each Table 3 cell (eq (11): mean over time of the RMS over runs, angles in degrees) of both
  builds, and the reference cell's Monte Carlo standard error (bootstrap over runs); criterion:
  |new - reference| <= 2 standard errors;
- the runs whose class (ok / excursion / diverged) differs: allowed only where either build
  classes the run as an excursion.

    python -m symkf.scenarios.launcher.lanes_equivalence [--runs 100] [--bootstrap 200]
"""
from __future__ import annotations

import argparse
import sys

import numpy as np

from symkf.models import launcher as L
from symkf.runtime import smooth
from symkf.scenarios.metrics import state_error
from .campaign import (ANGLE_STATES, STATE_NAMES, TUNING, Case, case_flight, initial_estimate, make_filter,
                       measurements, outcome)

#: The build whose numbers the comparison starts from: the scalar code of every sigma point.
REFERENCE_BUILD = {"ukf_lanes": False, "ukf_centre_free": False}
#: The build compared with it: the sigma points in SIMD lanes (an option; the library's default is scalar).
LANES_BUILD = {"ukf_lanes": True}
ESTIMATES = ("ukf", "ukf_rts", "ekf")
SEED = 2005


def run_errors(model, case: Case, runs: int, estimate: str) -> np.ndarray:
    """(runs, steps, 6) errors truth - estimate of one estimate over the case's first ``runs`` runs,
    as ``campaign.run_chunk`` makes them (the same draws, tuning, initial estimate and filter)."""
    measurement = L.RADAR_MEASUREMENTS[TUNING["stations"]]
    times, truth, track = case_flight(case.rate_hz, L.T_INSERTION, measurement)
    q, (x0, P0) = track.station_params(), initial_estimate(case, truth[0], TUNING["P0_floor"])
    family = estimate.split("_")[0]
    f = make_filter(model, family, x0, P0, TUNING, times[0])
    out = np.empty((runs, len(times), 6))
    for run in range(runs):
        f.x, f.P, f.t = x0, P0, times[0]
        result = f.run(times, measurements(SEED, case, run, track), measurement, q=q)
        x = smooth(f, result, errors="keep").x_smooth if estimate.endswith("_rts") else result.x
        out[run] = state_error(truth, x, ANGLE_STATES)
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


def compare_case(new, reference, case: Case, runs: int, estimate: str, draws: int) -> dict:
    e_new, e_ref = run_errors(new, case, runs, estimate), run_errors(reference, case, runs, estimate)
    kinds = [(outcome(a), outcome(b)) for a, b in zip(e_new, e_ref)]
    ok = np.array([a == "ok" and b == "ok" for a, b in kinds])
    rms_new, rms_ref = np.sqrt(np.mean(e_new**2, axis=1)), np.sqrt(np.mean(e_ref**2, axis=1))
    relative = np.abs(rms_new - rms_ref) / np.abs(rms_ref)
    cell_new, cell_ref = table_cell(e_new**2), table_cell(e_ref**2)
    se = bootstrap_se(e_ref**2, draws, np.random.default_rng(7))
    changed = [(run, a, b) for run, (a, b) in enumerate(kinds) if a != b]
    return {"case": case.label, "estimate": estimate, "ok_runs": int(ok.sum()),
            "max_rel_rms_ok": float(relative[ok].max()) if ok.any() else 0.0,
            "bitwise_equal_runs": int(sum(np.array_equal(a, b) for a, b in zip(e_new, e_ref))),
            "cell_new": cell_new, "cell_ref": cell_ref, "se": se, "within_2se": bool(np.all(np.abs(cell_new - cell_ref)
                                                                                          <= 2 * se)),
            "class_changes": changed, "class_changes_allowed": all("excursion" in (a, b) for _, a, b in changed)}


def report_lines(rows: list[dict]) -> list[str]:
    lines = []
    for r in rows:
        lines.append(f"{r['case']:<11} {r['estimate']:<7} ok runs {r['ok_runs']:>3}, bit-equal runs "
                     f"{r['bitwise_equal_runs']:>3}, max rel. diff of per-run RMS (ok runs) {r['max_rel_rms_ok']:.2e}, "
                     f"class changes {r['class_changes'] or 'none'}{'' if r['class_changes_allowed'] else ' (NOT ALLOWED)'}")
        for name, a, b, s in zip(STATE_NAMES, r["cell_new"], r["cell_ref"], r["se"]):
            flag = "" if abs(a - b) <= 2 * s else "   > 2 SE"
            lines.append(f"    {name:<6} new {a:.6g}  reference {b:.6g}  diff {a - b:+.3e}  SE {s:.3e}  "
                         f"|diff|/SE {abs(a - b) / s if s else 0.0:.3f}{flag}")
    return lines


def main(argv=None) -> int:
    from symkf.runtime import load
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=100)
    parser.add_argument("--bootstrap", type=int, default=200)
    parser.add_argument("--estimates", default=",".join(ESTIMATES))
    args = parser.parse_args(argv)
    new = load("launcher", backend="compiled", **LANES_BUILD)
    reference = load("launcher", backend="compiled", **REFERENCE_BUILD)
    rows = []
    for case in [Case(rate, init) for rate in L.RADAR_RATES_HZ for init in ("small", "large")]:
        for estimate in args.estimates.split(","):
            rows.append(compare_case(new, reference, case, args.runs, estimate, args.bootstrap))
            print("\n".join(report_lines(rows[-1:])), flush=True)
    verdicts = {}
    for r in rows:
        verdicts.setdefault(r["estimate"], []).append(r["within_2se"] and r["class_changes_allowed"]
                                                      and r["max_rel_rms_ok"] <= 1e-6)
    for estimate, met in verdicts.items():
        print(f"{estimate}: criterion {'met' if all(met) else 'NOT met'} in {sum(met)} of {len(met)} cases")
    return 0 if all(all(met) for met in verdicts.values()) else 1


if __name__ == "__main__":
    sys.exit(main())

"""Paper 004's EKF-vs-UKF Monte Carlo (Table 3, Figs 5-6) with ours beside.

4 cases (20 Hz and 10 Hz radar x small eq (9) and large eq (10) initial error), N runs each,
both filters fed the same radar draws, the whole run of each filter in one compiled C call.
Writes to --out: rms_table.csv (with the smoothers' columns ekf_rts, ukf_rts), rms_table.md,
fig_velocity_rms.png, fig_radius_rms.png, fig_nees.png, fig_smoother_rms.png (filter vs smoother
speed RMS(t); scenarios/launcher/figures.py), summary.json (totals and the paper's claims, each
in a plain sentence: scenarios/launcher/claims.py), series.nc (RMS(t) and NEES(t) per case, filter,
state and time, and every run's row: scenarios/launcher/series.py; ``symkf plot <out>`` redraws the
figures from it without running a filter). Tuning and truth: scenarios/launcher/campaign.py, truth.py.
"""
from __future__ import annotations

import csv
import json
import sys
import time
from pathlib import Path

import numpy as np

from symkf.models import launcher as L
from symkf.scenarios.claims import as_summary, print_claims
from . import campaign as C
from . import claims as paper_claims
from . import figures, series
from symkf.scenarios.campaign import ProgressBar, add_scheduler_arguments, scheduler_problem
from .campaign import FILTERS, PRESETS, SMOOTHED, STATE_NAMES, TUNING, Campaign, CaseResult, consistency

UNITS = dict(zip(STATE_NAMES, L.TABLE3_UNITS))


def add_arguments(parser) -> None:
    parser.add_argument("--runs", type=int, default=100, help="Monte Carlo runs per case (default 100)")
    parser.add_argument("--seed", type=int, default=2005, help="random seed (default 2005)")
    parser.add_argument("--rates", default="20,10", help="radar rates in Hz, comma-separated (default 20,10)")
    parser.add_argument("--out", default=None,
                        help="output folder (default results/launcher, results/launcher-paper-like for that preset)")
    parser.add_argument("--filters", default="correct", choices=sorted(PRESETS),
                        help="filter configuration: 'correct' (RK4 split at events, exact Jacobian, Q from the "
                             "model's neglected terms; default) or 'paper-like' (EKF Euler + Phi = I + A dt, "
                             "UKF RK4, events integrated across: the best reading of what the paper ran)")
    parser.add_argument("--duration", type=float, default=L.T_INSERTION,
                        help=f"seconds of flight to filter (default {L.T_INSERTION}, the whole flight)")
    parser.add_argument("--kappa", type=float, default=TUNING["kappa"],
                        help=f"UKF sigma-point scaling, n + kappa > 0 (default {TUNING['kappa']})")
    parser.add_argument("--q-scale", type=float, default=1.0,
                        help="multiply the preset's process-noise density Q by this factor (default 1)")
    parser.add_argument("--stations", default=None, choices=sorted(L.RADAR_MEASUREMENTS),
                        help="radar stations on the 'spherical' Earth (paper-like's) or 'wgs84' geodetic (correct's); "
                             "default: the preset's")
    parser.add_argument("--ekf-q-scale", type=float, default=1.0, help="multiply the EKF's Q only (default 1)")
    parser.add_argument("--ukf-q-scale", type=float, default=1.0, help="multiply the UKF's Q only (default 1)")
    parser.add_argument("--p0-floor", default=None,
                        help="six comma-separated floors of the initial standard deviations (m/s, rad, rad, m, "
                             "rad, rad; default: the preset's)")
    parser.add_argument("--exact", action="store_true",
                        help="every run the flight bundle's numbers bit for bit (the lockstep loops call libm "
                             "lane by lane; about 1.5x the CPU); default: libmvec in the prediction, whose "
                             "round-off moves results within the Monte Carlo error")
    parser.add_argument("--quiet", action="store_true", help="no progress bar, no table")
    add_scheduler_arguments(parser)


def run(args) -> int:
    try:
        rates = tuple(int(r) for r in str(args.rates).split(",") if r.strip())
        tuning = tuning_from_args(args)
    except ValueError as exc:
        print(f"symkf compare launcher: {exc}", file=sys.stderr)
        return 2
    bad = [r for r in rates if r not in L.RADAR_RATES_HZ]
    scales = (args.q_scale, args.ekf_q_scale, args.ukf_q_scale)
    if bad or not rates or args.runs < 1 or not 0 < args.duration <= L.T_INSERTION or not args.kappa > -6 \
            or not all(s > 0 and np.isfinite(s) for s in scales):
        print(f"symkf compare launcher: rates must be among {L.RADAR_RATES_HZ}, runs >= 1, "
              f"0 < duration <= {L.T_INSERTION}, kappa > -6 and every q-scale > 0", file=sys.stderr)
        return 2
    problem = scheduler_problem(args.scheduler, args.workers)
    if problem:
        print(f"symkf compare launcher: {problem}", file=sys.stderr)
        return 2
    progress = None if args.quiet else ProgressBar()
    start = time.perf_counter()
    campaign = Campaign(args.runs, args.seed, rates, args.duration, workers=args.workers, progress=progress,
                        tuning=tuning, scheduler=args.scheduler, preset=args.filters, exact=args.exact)   # builds if stale
    built = time.perf_counter() - start
    results = campaign.run()
    wall = time.perf_counter() - start - built
    out = Path(args.out or ("results/launcher" if args.filters == "correct" else f"results/launcher-{args.filters}"))
    out.mkdir(parents=True, exist_ok=True)
    rows = table_rows(results)
    write_csv(out / "rms_table.csv", rows)
    header = f"Filters: {args.filters}; arithmetic: {campaign.arithmetic()}\n"
    (out / "rms_table.md").write_text(header + "\n" + markdown_table(results, rows))
    checked = paper_claims.claims(results)
    summary = {**make_summary(results, args, wall, campaign, checked), "build_s": built}
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    config = figures.configuration(args.filters, args.runs, args.seed)
    figures.plot_rms(results, "V", "Speed error RMS (m/s)", out / "fig_velocity_rms.png", config)
    figures.plot_rms(results, "r", "Radius error RMS (m)", out / "fig_radius_rms.png", config)
    figures.plot_nees(results, out / "fig_nees.png", config)
    figures.plot_smoother_rms(results, "V", "Speed error RMS (m/s)", out / "fig_smoother_rms.png", config)
    saved = series.save(results, out, config, {"preset": args.filters, "runs": args.runs, "seed": args.seed})
    written = time.perf_counter() - start - built - wall
    if not args.quiet:
        print("\n" + header + markdown_table(results, rows))
        print(f"  mean |log10(ours/paper)| over Table 3's {summary['table3_cells']} cells: "
              f"{summary['mean_abs_log10_vs_paper']:.3f}")
        for label, case in summary["cases"].items():
            print(f"  {label}: average NEES inside its 95 % band (outside {C.EVENT_WINDOW_S:g} s after events) "
                  + ", ".join(f"{f.upper()} {_percent(case[f]['fraction_inside_band_outside_event_windows'])}"
                              for f in FILTERS))
        print("The paper's claims, checked on these runs:")
        print_claims(checked)
        print(f"wrote {out}/ ({saved.name}) in {built + wall + written:.1f} s: build {built:.1f} s, campaign {wall:.1f} s "
              f"({campaign.stats.executor}, {campaign.stats.workers} workers; {campaign.stats.cpu_s:.1f} CPU-s in this "
              f"process and the worker processes it started), tables and figures {written:.1f} s")
    return 0


def _percent(value) -> str:
    return "n/a (no time outside the windows)" if value is None else f"{value:.0%}"


# ---------------------------------------------------------------------- tables
def table_rows(results: list[CaseResult]) -> list[dict]:
    rows = []
    for result in results:
        key = (result.case.rate_hz, result.case.initial_error)
        ours = {family: result.whole_flight(family) for family in FILTERS}
        for i, state in enumerate(STATE_NAMES):
            paper_ekf, paper_ukf = L.TABLE3[key][state]
            rows.append({"state": state, "unit": UNITS[state], "case": result.case.label,
                         "ekf": float(ours["ekf"][i]), "ukf": float(ours["ukf"][i]),
                         "paper_ekf": paper_ekf, "paper_ukf": paper_ukf,
                         **{s: float(result.whole_flight(s)[i]) for s in SMOOTHED}})
    return rows


def write_csv(path: Path, rows: list[dict]) -> None:
    with open(path, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


def markdown_table(results: list[CaseResult], rows: list[dict]) -> str:
    """Table 3's layout: states as rows, case x filter as columns, 'ours (paper)' in each cell."""
    cases = [r.case.label for r in results]
    head = "| State | " + " | ".join(f"{c} EKF | {c} UKF" for c in cases) + " |"
    rule = "|---" * (1 + 2 * len(cases)) + "|"
    lines = ["Whole-flight RMS error, eq (11): ours (paper Table 3)", "", head, rule]
    for state in STATE_NAMES:
        cells = []
        for case in cases:
            row = next(r for r in rows if r["state"] == state and r["case"] == case)
            cells += [f"{row['ekf']:.3g} ({row['paper_ekf']:.3g})", f"{row['ukf']:.3g} ({row['paper_ukf']:.3g})"]
        lines.append(f"| {state} ({UNITS[state]}) | " + " | ".join(cells) + " |")
    lines += ["", "Fixed-interval smoothing of the same runs (RTS over the EKF, unscented RTS over the UKF): "
              "smoothed (filtered)", "", "| State | " + " | ".join(f"{c} EKF+RTS | {c} UKF+RTS" for c in cases) + " |",
              rule]
    for state in STATE_NAMES:
        cells = []
        for case in cases:
            row = next(r for r in rows if r["state"] == state and r["case"] == case)
            cells += [f"{row[f + '_rts']:.3g} ({row[f]:.3g})" for f in FILTERS]
        lines.append(f"| {state} ({UNITS[state]}) | " + " | ".join(cells) + " |")
    runs = results[0].errors["ekf"].runs
    for kind, threshold in (("diverged", f"angle error still above {C.DIVERGED_ANGLE_RAD} rad in the second half"),
                            ("excursion", f"angle error above {C.EXCURSION_ANGLE_RAD} rad early, then recovered")):
        listed = [f"{r.case.label} {family.upper()} {getattr(r, kind + '_runs')[family]}" for r in results
                  for family in FILTERS if getattr(r, kind + "_runs")[family]]
        lines += ["", f"Runs {kind} ({threshold}), of {runs}: " + ("; ".join(listed) if listed else "none")]
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------- summary and claims
def tuning_from_args(args) -> dict:
    """The preset's tuning with the command line's knobs applied (raises ValueError on bad input)."""
    base = PRESETS[args.filters]["tuning"]
    tuning = {"kappa": args.kappa, "Q": base["Q"] * args.q_scale,
              "ekf_q_scale": args.ekf_q_scale, "ukf_q_scale": args.ukf_q_scale}
    if args.stations is not None:
        tuning["stations"] = args.stations
    if args.p0_floor is not None:
        floor = np.array([float(v) for v in str(args.p0_floor).split(",")])
        if floor.shape != (6,) or not np.all(np.isfinite(floor) & (floor > 0)):
            raise ValueError(f"--p0-floor needs six positive numbers, got '{args.p0_floor}'")
        tuning["P0_floor"] = floor
    return tuning


def mean_abs_log10_vs_paper(rows: list[dict]) -> float:
    """Mean over Table 3's cells (state x case x filter) of |log10(ours / paper)|."""
    return float(np.mean([abs(np.log10(row[f] / row[f"paper_{f}"])) for row in rows for f in FILTERS]))


def make_summary(results: list[CaseResult], args, wall: float, campaign: Campaign, checked: list) -> dict:
    """Totals per case and estimate and the checked claims; every run's row is in the series file
    (series.nc: run_outcome, run_rms, ...), so this file stays small at any run count."""
    cases = {}
    for result in results:
        entry = {}
        for family in FILTERS + SMOOTHED:
            entry[family] = {
                "rms_eq11": dict(zip(STATE_NAMES, result.whole_flight(family).tolist())),
                **consistency(result, family),
                "wall_s": result.wall_s[family],
                "cpu_s": result.cpu_s[family],
                "steps": int(len(result.times) * result.errors[family].runs),
                "us_per_step_in_run": 1e6 * result.wall_s[family] / (len(result.times) * result.errors[family].runs),
                "failed_steps": result.failed_steps[family],
                "runs": result.errors[family].runs,
                "diverged_run_count": len(result.diverged_runs[family]),
                "excursion_run_count": len(result.excursion_runs[family]),
                "rms_eq11_without_diverged_runs": dict(zip(STATE_NAMES, result.whole_flight(family, True).tolist())),
            }
        cases[result.case.label] = entry
    rows = table_rows(results)
    stats = campaign.stats
    return {"runs": args.runs, "seed": args.seed, "duration_s": args.duration, "wall_s": wall,
            "executor": stats.executor, "workers": stats.workers, "campaign_cpu_s": stats.cpu_s,
            "filters": campaign.preset, "codegen": campaign.codegen, "units": UNITS,
            "tuning": {k: np.asarray(v).tolist() for k, v in campaign.tuning.items()},
            "mean_abs_log10_vs_paper": mean_abs_log10_vs_paper(rows), "table3_cells": 2 * len(rows),
            "cases": cases, "claims": as_summary(checked),
            "ekf_over_ukf_ratio": {r.case.label: dict(zip(STATE_NAMES, np.round(paper_claims.ratio(r), 3).tolist()))
                                   for r in results}}

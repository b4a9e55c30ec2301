"""Paper 001, Fig 3 on real recordings: Euler angles (5) for several gains β, accuracy and oscillation.

    symkf compare marg --data broad/01_undisturbed_slow_rotation_A.mat \\
        --beta 0.01,0.5 --out results/marg [--sweep] [--form simple|full] [--mode marg|imu]

(BROAD's trials, CC BY 4.0: https://github.com/dlaidig/broad; the x-io Fusion example CSV, MIT:
https://github.com/xioTechnologies/Fusion.)

For every β: the Euler angles (5) of the estimate vs time (with the optical reference when the
recording has one; BROAD trials do, the x-io CSV does not), the BROAD error metric (total,
heading, inclination RMSE over movement phases, deg; ``scenarios/marg/broad_metric.py``), and two measures of
the paper's claim that a larger β brings high-frequency oscillation:

- ``hf_rms_deg``: RMS of the Euler angles' content above ``--hf-cutoff`` Hz (default 5 Hz; body
  motion in these recordings is well below it), from the FFT of the unwrapped, detrended angles;
- ``diff_rms_deg``: RMS of the first difference of the unwrapped Euler angles (deg per sample);
- ``still_diff_rms_deg`` (BROAD): the same over rest phases (``movement == 0``) only, where the
  sensor does not move and every change is estimator oscillation;
- ``error_hf_rms_deg`` (BROAD): RMS above the cutoff of the error rotation vector
  (``q_est ⊗ q_ref⁻¹``, earth frame; the norm over its three components), i.e. the
  oscillation of the estimate about the optical reference, motion removed.

**Over a folder of BROAD trials** (``--data DIR``, ``.hdf5`` or ``.mat`` files): one table, per
trial, the total / heading / inclination RMSE of Madgwick's filter at β = 0.041, at its best β
(the sweep grid plus 0.041, chosen per trial: an oracle), and of the generated multiplicative
EKF of ``models/marg_mekf.py`` (one parameter set for every trial) and of its fixed-interval
smoothing (``mekf_rts``: the generated error-state RTS smoother over the offline forward run of
``scenarios/marg/mekf_offline.py``: the same parameters, the magnetometer decided two-sided, the
gyro read half a sample later and its scale factors estimated); ``series.nc`` holds the rows
(``rmse``: trial x filter x metric) and ``summary.json`` ``mean_total_rmse_deg`` (filter name ->
mean total RMSE over the trials):

    symkf compare marg --data broad --out results/marg

Both are also given for the optical reference (NaN gaps linearly interpolated) as the floor of
real motion. ``--sweep`` adds RMSE and oscillation vs β on a log grid and marks the β of least
total RMSE (beyond the paper). Everything goes to ``<out>/summary.json`` and PNG figures; the
Euler angles per β and sample to ``<out>/series.nc`` (scenarios/marg/series.py), from which
``symkf plot <out>`` redraws the figures.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from symkf.models.marg import ALPHA_DEFAULT, BETA_MADGWICK
from symkf.runtime import load
from symkf.scenarios.marg.filter import make_filter
from symkf.scenarios import results as R
from symkf.scenarios.marg import mekf, mekf_offline, series
from symkf.scenarios.marg.data import (WHERE_BROAD, WHERE_XIO, Recording, broad_trials, data_dir, load_recording,
                                       run_recording)
from symkf.scenarios.marg.broad_metric import broad_errors, error_rotation_vectors, euler_angles, from_enu, to_enu

DEFAULT_DATA = data_dir() / "broad" / "01_undisturbed_slow_rotation_A.mat"
SWEEP_BETAS = np.round(np.logspace(-3, 0, 19), 5)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA,
                        help="a BROAD .mat/.hdf5 or an x-io .csv recording, or a folder of BROAD trials (one table)")
    parser.add_argument("--beta", type=_float_list, default=[0.01, 0.5], help="comma-separated gains (rad/s)")
    parser.add_argument("--out", type=Path, default=Path("results") / "marg")
    parser.add_argument("--sweep", action="store_true", help="also sweep beta on a log grid and mark the best")
    parser.add_argument("--form", choices=("simple", "full"), default="simple",
                        help="simplified form (31) (the paper's Fig 3) or full form (26)-(30)")
    parser.add_argument("--mode", choices=("marg", "imu"), default="marg", help="9-axis or 6-axis")
    parser.add_argument("--alpha", type=float, default=ALPHA_DEFAULT, help="eq (28), full form only")
    parser.add_argument("--hf-cutoff", type=float, default=5.0, help="Hz, for the oscillation measure")
    parser.add_argument("--zoom", type=float, nargs=2, default=(0.0, 20.0), metavar=("T0", "T1"),
                        help="time window (s) of the zoomed Euler-angle figure")
    parser.add_argument("--no-plots", action="store_true")


def _float_list(text: str) -> list[float]:
    try:
        values = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None
    if not values or any(v < 0 for v in values):
        raise argparse.ArgumentTypeError("expected one or more gains >= 0")
    return values


# ---------------------------------------------------------------------- measures
def _unwrapped_degrees(angles: np.ndarray) -> np.ndarray:
    return np.degrees(np.unwrap(angles, axis=0))


def _fill_gaps(series: np.ndarray) -> np.ndarray:
    """Linear interpolation over NaN rows (the optical reference loses markers now and then)."""
    out = series.copy()
    index = np.arange(series.shape[0])
    for j in range(series.shape[1]):
        good = np.isfinite(series[:, j])
        out[:, j] = np.interp(index, index[good], series[good, j])
    return out


def high_frequency_rms(series: np.ndarray, rate_hz: float, cutoff_hz: float) -> np.ndarray:
    """Per column, the RMS of the content above ``cutoff_hz`` (NaN gaps interpolated, linear trend removed)."""
    filled = _fill_gaps(series)
    n = filled.shape[0]
    trend = np.linspace(0, 1, n)[:, None] * (filled[-1] - filled[0]) + filled[0]   # no step at the wrap-around
    spectrum = np.fft.rfft(filled - trend, axis=0)
    spectrum[np.fft.rfftfreq(n, 1 / rate_hz) < cutoff_hz] = 0
    return np.sqrt(np.mean(np.fft.irfft(spectrum, n=n, axis=0) ** 2, axis=0))


def oscillation(angles: np.ndarray, rate_hz: float, cutoff_hz: float,
                still: np.ndarray | None = None) -> dict[str, list[float]]:
    """High-frequency RMS above ``cutoff_hz`` and first-difference RMS of Euler angles (N, 3) rad, deg.

    With ``still`` (a per-sample flag of rest phases, e.g. BROAD's ``movement == 0``), also the
    first-difference RMS over consecutive still samples only: there the sensor does not move, so
    all of it is estimator oscillation.
    """
    deg = _unwrapped_degrees(_fill_gaps(angles))
    diff = np.diff(deg, axis=0)
    result = {"hf_rms_deg": high_frequency_rms(deg, rate_hz, cutoff_hz).tolist(),
              "diff_rms_deg": np.sqrt(np.mean(diff**2, axis=0)).tolist()}
    if still is not None:
        both = still[1:] & still[:-1]
        result["still_diff_rms_deg"] = np.sqrt(np.mean(diff[both] ** 2, axis=0)).tolist()
    return result


def _still(recording: Recording) -> np.ndarray | None:
    return None if recording.movement is None else ~recording.movement


# ---------------------------------------------------------------------- one beta
def run_beta(compiled, recording: Recording, beta: float, args) -> tuple[dict, np.ndarray]:
    filt = make_filter(compiled, args.form, beta=beta, alpha=args.alpha)
    result = run_recording(compiled, filt, recording, args.mode)
    angles = euler_angles(result.x)
    rate = 1 / np.median(recording.dt[1:])
    entry = {"beta": beta, "failed_steps": int(result.failed_steps.size),
             "oscillation": oscillation(angles, rate, args.hf_cutoff, _still(recording))}
    if recording.reference is not None:
        entry["broad_rmse_deg"] = broad_errors(result.x, recording)
        error = np.degrees(error_rotation_vectors(to_enu(result.x), recording.reference))
        error_hf = high_frequency_rms(error, rate, args.hf_cutoff)
        entry["oscillation"]["error_hf_rms_deg"] = float(np.linalg.norm(error_hf))
    return entry, angles


def sweep(compiled, recording: Recording, args) -> dict:
    rows = [run_beta(compiled, recording, float(beta), args)[0] for beta in SWEEP_BETAS]
    out = {"betas": SWEEP_BETAS.tolist(), "rows": rows}
    if recording.reference is not None:
        totals = [r["broad_rmse_deg"]["total"] for r in rows]
        best = int(np.argmin(totals))
        out["best_beta"] = float(SWEEP_BETAS[best])
        out["best_rmse_deg"] = rows[best]["broad_rmse_deg"]
    return out


# ---------------------------------------------------------------------- command
def run(args) -> int:
    if args.data.is_dir():
        return run_trials(args)
    try:
        recording = load_recording(args.data)
    except (FileNotFoundError, ValueError) as exc:
        print(f"symkf compare marg: {exc}\n  {WHERE_BROAD}\n  {WHERE_XIO}")
        return 1
    start = time.perf_counter()
    compiled = load("marg")                      # builds if the library is stale
    built = time.perf_counter() - start
    args.out.mkdir(parents=True, exist_ok=True)
    per_beta, entries = [], []
    for beta in args.beta:
        entry, angles = run_beta(compiled, recording, beta, args)
        entries.append(entry)
        per_beta.append((beta, angles))
    rate = 1 / np.median(recording.dt[1:])
    summary = {"recording": str(args.data), "source": recording.source, "samples": len(recording),
               "rate_hz": rate, "form": args.form, "mode": args.mode,
               "alpha": args.alpha if args.form == "full" else None,
               "hf_cutoff_hz": args.hf_cutoff, "per_beta": entries,
               "euler_convention": "eq (5) applied to q* (sensor yaw psi, pitch theta, roll phi; Z-Y-X), "
                                   "earth frame north-west-up"}
    reference_angles = None
    if recording.reference is not None:
        reference_angles = euler_angles(from_enu(recording.reference))
        reference_angles[~np.isfinite(recording.reference).all(axis=1)] = np.nan   # markers lost
        summary["reference_oscillation"] = oscillation(reference_angles, rate, args.hf_cutoff, _still(recording))
    if args.sweep:
        summary["sweep"] = sweep(compiled, recording, args)
    filtered = time.perf_counter() - start - built
    saved = series.make_series(recording, per_beta, reference_angles, args, summary.get("sweep"))
    R.save(saved, args.out)                      # symkf plot <out> redraws the figures from it
    figures = [] if args.no_plots else [str(path) for path in series.redraw(saved, args.out)]
    summary["figures"] = figures
    if args.mode == "imu":
        summary["note"] = ("6-axis mode: the heading is unobservable (initial heading from a sensor axis), so "
                           "BROAD total/heading errors are not meaningful; read the inclination error")
    (args.out / "summary.json").write_text(json.dumps(summary, indent=1))
    _print_table(summary)
    print(f"wrote {args.out}/ in {time.perf_counter() - start:.1f} s: build {built:.1f} s, filters {filtered:.1f} s, "
          f"figures and series {time.perf_counter() - start - built - filtered:.1f} s")
    return 0


def _print_table(summary: dict) -> None:
    print(f"{summary['recording']}  ({summary['samples']} samples, {summary['rate_hz']:.1f} Hz, "
          f"form {summary['form']}, mode {summary['mode']})")
    print(f"{'beta':>8} {'total':>7} {'heading':>8} {'incl':>6} | HF RMS > {summary['hf_cutoff_hz']:g} Hz "
          "psi/theta/phi [deg] | diff RMS [deg/sample] | still diff RMS | error HF")
    rows = [(e["beta"], e) for e in summary["per_beta"]]
    for beta, e in rows:
        rmse = e.get("broad_rmse_deg")
        acc = (f"{rmse['total']:7.2f} {rmse['heading']:8.2f} {rmse['inclination']:6.2f}" if rmse
               else f"{'-':>7} {'-':>8} {'-':>6}")
        hf = "/".join(f"{v:.4f}" for v in e["oscillation"]["hf_rms_deg"])
        df = "/".join(f"{v:.4f}" for v in e["oscillation"]["diff_rms_deg"])
        still = "/".join(f"{v:.5f}" for v in e["oscillation"].get("still_diff_rms_deg", []))
        err_hf = e["oscillation"].get("error_hf_rms_deg")
        print(f"{beta:8g} {acc} | {hf} | {df} | {still} | " + ("" if err_hf is None else f"{err_hf:.4f}"))
    if "reference_oscillation" in summary:
        ref = summary["reference_oscillation"]
        print(f"{'optical reference':>32} | " + "/".join(f"{v:.4f}" for v in ref["hf_rms_deg"]) + " | "
              + "/".join(f"{v:.4f}" for v in ref["diff_rms_deg"]) + " | "
              + "/".join(f"{v:.5f}" for v in ref.get("still_diff_rms_deg", [])))
    if "sweep" in summary and "best_beta" in summary["sweep"]:
        best = summary["sweep"]["best_rmse_deg"]
        print(f"sweep: best beta = {summary['sweep']['best_beta']:g} rad/s, total RMSE {best['total']:.2f} deg "
              f"(heading {best['heading']:.2f}, inclination {best['inclination']:.2f})")


# ---------------------------------------------------------------------- a folder of BROAD trials
FILTERS = ("madgwick_0.041", "madgwick_best", "mekf", "mekf_rts")


def trial_row(madgwick, mekf_model, offline_model, recording: Recording, args) -> dict:
    """One trial: Madgwick at β = 0.041, at its best β of the grid, and the generated MEKF."""
    betas = sorted(set(SWEEP_BETAS.tolist()) | {BETA_MADGWICK})
    errors = {beta: broad_errors(run_recording(madgwick, make_filter(madgwick, args.form, beta=beta, alpha=args.alpha),
                                               recording).x, recording) for beta in betas}
    best = min(betas, key=lambda beta: errors[beta]["total"])
    result = mekf.run_recording(mekf_model, recording)
    smoothed = mekf_offline.smooth_recording(offline_model, recording)
    return {"trial": recording.name, "samples": len(recording), "best_beta": best,
            "madgwick_0.041": errors[BETA_MADGWICK], "madgwick_best": errors[best],
            "mekf": broad_errors(result.q, recording, frame="enu"),
            "mekf_rts": broad_errors(smoothed.x_smooth[:, :4], recording, frame="enu"),
            "mekf_failed_steps": int(result.failed_steps.size), "mekf_gated_steps": result.gated_steps,
            "mekf_rts_failed_steps": int(smoothed.failed_steps.size),
            "mekf_rts_gyro_scale_error_percent": (100 * smoothed.x_smooth[0, 7:]).tolist(),
            "mekf_heading_used_fraction": float(mekf.masks(recording)[:, 3].mean())}


def run_trials(args) -> int:
    try:
        paths = broad_trials(args.data)
        recordings = [load_recording(path) for path in paths]
    except (FileNotFoundError, ValueError) as exc:
        print(f"symkf compare marg: {exc}\n  {WHERE_BROAD}")
        return 1
    missing = [r.name for r in recordings if r.reference is None]
    if missing:
        print(f"symkf compare marg: {missing} have no optical reference")
        return 1
    madgwick, mekf_model, offline_model = load("marg"), load("marg_mekf"), mekf_offline.load_model()
    rows = []
    for recording in recordings:
        try:
            rows.append(trial_row(madgwick, mekf_model, offline_model, recording, args))
        except ValueError as exc:          # e.g. NaN IMU samples, or no movement phase to score
            detail = str(exc).removeprefix(f"{recording.name}: ")
            print(f"symkf compare marg: trial {recording.name}: {detail}")
            return 1
    summary = {"data": str(args.data), "trials": [str(p) for p in paths], "form": args.form,
               "mean_total_rmse_deg": {f: float(np.mean([r[f]["total"] for r in rows])) for f in FILTERS},
               "metric": "BROAD RMSE over movement phases, deg (the benchmark's own error metric)",
               "note": "madgwick_best is an oracle: its beta is chosen per trial against the reference; "
                       "mekf uses one parameter set (models/marg_mekf.py, scenarios/marg/mekf.py) for every trial"}
    args.out.mkdir(parents=True, exist_ok=True)
    R.save(series.trials_series(rows, FILTERS, {"data": str(args.data), "form": args.form}), args.out)
    (args.out / "summary.json").write_text(json.dumps(summary, indent=1))
    print_trials_table(summary, rows)
    return 0


def print_trials_table(summary: dict, rows: list[dict]) -> None:
    print(f"BROAD RMSE [deg] total / heading / inclination, {len(rows)} trials from {summary['data']}")
    print(f"{'trial':<36} {'Madgwick beta=0.041':>21} {'Madgwick best beta':>27} {'MEKF (marg_mekf)':>21}"
          f" {'MEKF + RTS smoother':>21}")
    for r in rows:
        cells = [" / ".join(f"{r[f][k]:5.2f}" for k in ("total", "heading", "inclination")) for f in FILTERS]
        print(f"{r['trial']:<36} {cells[0]:>21} {cells[1]:>18} (b={r['best_beta']:<6g}) {cells[2]:>21} {cells[3]:>21}")
    means = summary["mean_total_rmse_deg"]
    print(f"{'mean total':<36} {means[FILTERS[0]]:>21.2f} {means[FILTERS[1]]:>27.2f} {means[FILTERS[2]]:>21.2f}"
          f" {means[FILTERS[3]]:>21.2f}")

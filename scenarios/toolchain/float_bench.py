"""Single precision beside double: each figure of the float build next to the double build's, on the same draws.

Every figure from the float build (``precision="float"``) beside the same figure from the default
double build.

    symkf bench float [--runs 100] [--attitude-runs 2] [--attitude-duration 600] [--geo-duration 1000]
                      [--square-root-runs 10] [--model FILE]
                      [--json] [--out FILE] [--skip-launcher] [--skip-attitude] [--skip-marg] [--skip-geo]
                      [--skip-square-root]

- launcher (paper 004): the 20 Hz small-error case (eq 9) of the campaign (preset ``correct``,
  seed 2005): ``--runs`` Monte Carlo runs of the whole flight through the EKF and the UKF, each
  run by the campaign's own task (:func:`symkf.scenarios.launcher.campaign.run_chunk`) once per
  build. Whole-flight RMS (eq 11) of r and V, refused steps (status other than 0), diverged runs
  (the campaign's definition) and float / double. ``--runs 100`` (the default) is the case exactly
  as ``symkf compare launcher`` runs it. The float build carries the scaled state (codegen/scaling.py).
- attitude (paper 000, scenario I): ``--attitude-runs`` runs of ``--attitude-duration`` s, MEKF
  and UKF (:func:`symkf.scenarios.attitude.compare.one_run`): attitude RMS over the second half.
- marg (paper 001, BROAD trials in ``$SYMKF_DATA_DIR/broad``): the generated MEKF of
  ``models/marg_mekf.py`` and the gradient-descent filter (simplified form, beta = 0.041): mean
  total RMSE over the trials.
- geo (paper 003, Table 7 case 3 with bias and noise, and case 4 with gyros A and C failed): the
  closed loop of :mod:`symkf.scenarios.geo.closed_loop` for ``--geo-duration`` s, truth, sensors
  and controller in double, only the continuous-discrete EKF from the float build: RMS of the
  attitude estimation error and of the true attitude over the second half (deg). A refused
  update stops the loop (SymkfError) and is reported as such.
- square-root forms (:mod:`symkf.scenarios.toolchain.square_root_float`): EKF, UKF, SR-EKF and
  SR-UKF on the launcher's 20 Hz small-error case (``--square-root-runs`` runs) in double, float
  with the declared scaling and float without it; the MEKF and SR-MEKF on attitude scenario I
  (``--attitude-runs``, ``--attitude-duration``) and the CD-EKF and SR-CD-EKF in the geo closed
  loops (``--geo-duration``), double and float (skipped with ``--skip-attitude``, ``--skip-geo``); and, with ``--model FILE``, on a user model file
  with a truth simulation (e.g. tests/models/leo_od_model.py), double and float.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from symkf.models import launcher as L
from symkf.scenarios import timing
from symkf.scenarios.campaign import model_key
from symkf.scenarios.report import emit

PRECISIONS = ("double", "float")


def add_arguments(parser) -> None:
    parser.add_argument("--runs", type=int, default=100, help="launcher Monte Carlo runs (default 100, the campaign's)")
    parser.add_argument("--attitude-runs", type=int, default=2, help="attitude Monte Carlo runs (default 2)")
    parser.add_argument("--attitude-duration", type=float, default=600.0, help="attitude seconds per run (default 600)")
    parser.add_argument("--geo-duration", type=float, default=1000.0, help="geo closed-loop seconds (default 1000)")
    parser.add_argument("--skip-launcher", action="store_true")
    parser.add_argument("--skip-attitude", action="store_true")
    parser.add_argument("--skip-marg", action="store_true")
    parser.add_argument("--skip-geo", action="store_true")
    parser.add_argument("--square-root-runs", type=int, default=10,
                        help="launcher runs of the EKF/UKF/SR-EKF/SR-UKF rows (default 10)")
    parser.add_argument("--model", default=None, help="a model file with bench_case(rng): its filters, double and float")
    parser.add_argument("--skip-square-root", action="store_true")
    parser.add_argument("--json", action="store_true", help="print the results as JSON only")
    parser.add_argument("--out", type=Path, default=None, help="also write the JSON here")


def codegen(precision: str) -> dict:
    """The codegen overrides of a precision (the double build is the default configuration)."""
    return {} if precision == "double" else {"precision": precision}


def launcher(runs: int, seed: int = 2005) -> dict:
    """Whole-flight RMS and refused steps of EKF and UKF, 20 Hz small error, per precision."""
    from symkf.scenarios.launcher import campaign as C
    case, out = C.Case(20, "small"), {}
    for precision in PRECISIONS:
        chunk, wall, _ = timing.timed(lambda: C.run_chunk(model_key("launcher", **codegen(precision)), case, seed,
                                                          (0, runs), L.T_INSERTION, C.TUNING))
        for family in C.FILTERS:
            rms = chunk.errors[family].rms()
            whole = C.whole_flight_mean(np.where(C.ANGLE_STATES, np.degrees(rms), rms))
            per_run = chunk.per_run[family]
            failed = per_run[:, C.PER_RUN_COLUMNS.index("failed_steps")]
            diverged = per_run[:, C.PER_RUN_COLUMNS.index("diverged")]
            out.setdefault(family, {})[precision] = {
                "r_rms_m": float(whole[3]), "V_rms_m_s": float(whole[0]), "refused_steps": int(failed.sum()),
                "diverged_runs": int(diverged.sum()), "runs": runs, "filter_seconds": chunk.wall_s[family], "wall_seconds": wall}
    return out


def attitude(runs: int, duration: float, seed: int = 2008) -> dict:
    """Attitude RMS (deg) over the second half of scenario I, MEKF and UKF, per precision."""
    from symkf.scenarios.attitude import compare as A
    out = {}
    for precision in PRECISIONS:
        key = model_key("attitude", **codegen(precision))
        results = [A.one_run(key, "I", duration, A.SCENARIO_I_BIAS, seed, run, A.DEFAULT_KAPPA) for run in range(runs)]
        for family in A.FILTERS:
            half = [r[family]["angle"][len(r[family]["angle"]) // 2:] for r in results]
            out.setdefault(family, {})[precision] = {
                "attitude_rms_deg": float(np.sqrt(np.mean(np.square(half)))),
                "refused_steps": int(sum(r[family]["failed"] for r in results)), "runs": runs,
                "duration_s": duration}
    return out


def marg() -> dict:
    """Mean total RMSE (deg) over the BROAD trials: MEKF and gradient descent (simple, beta 0.041)."""
    from symkf.models.marg import BETA_MADGWICK
    from symkf.runtime import load
    from symkf.scenarios.marg.filter import make_filter
    from symkf.scenarios.marg import mekf as ekf
    from symkf.scenarios.marg.data import broad_trials, data_dir, load_recording, run_recording
    from symkf.scenarios.marg.broad_metric import broad_errors
    try:
        recordings = [load_recording(path) for path in broad_trials(data_dir() / "broad")]
    except (OSError, ValueError) as exc:
        return {"skipped": str(exc)}
    out = {}
    for precision in PRECISIONS:
        mekf, gd = load("marg_mekf", **codegen(precision)), load("marg", **codegen(precision))
        rows = {"mekf": [], "gd_simple": []}
        refused = {"mekf": 0, "gd_simple": 0}
        for recording in recordings:
            run = ekf.run_recording(mekf, recording)
            rows["mekf"].append(broad_errors(run.q, recording, frame="enu")["total"])
            refused["mekf"] += run.failed_steps.size
            run = run_recording(gd, make_filter(gd, "simple", beta=BETA_MADGWICK), recording)
            rows["gd_simple"].append(broad_errors(run.q, recording)["total"])
            refused["gd_simple"] += run.failed_steps.size
        for family, values in rows.items():
            out.setdefault(family, {})[precision] = {"mean_total_rmse_deg": float(np.mean(values)),
                                                     "refused_steps": refused[family], "trials": len(values)}
    return out


#: The geo closed loops compared: Table 7 case 3 (bias and noise on) and case 4 (gyros A, C failed).
GEO_RUNS = {"case3_bias_noise": {}, "case4_fail_AC": {"failed_gyros": ("A", "C")}}


def geo(duration: float) -> dict:
    """The geo closed loops with the EKF from each build (truth, sensors and control in double)."""
    from symkf.runtime import load
    from symkf.scenarios.toolchain.square_root_float import geo_loop
    double = load("geo_satellite")
    builds = {"double": double, "float": load("geo_satellite", precision="float")}
    return {label: {"cd_ekf": {precision: geo_loop(double, compiled, "cd_ekf", duration, options)
                               for precision, compiled in builds.items()}}
            for label, options in GEO_RUNS.items()}


def run(args) -> int:
    if args.runs < 1 or args.attitude_runs < 1 or args.square_root_runs < 1 or not args.geo_duration > 0:
        raise SystemExit("--runs, --attitude-runs and --square-root-runs must be >= 1 and --geo-duration > 0")
    result = {}
    if not args.skip_launcher:
        result["launcher_20Hz_small"] = launcher(args.runs)
    if not args.skip_attitude:
        result["attitude_scenario_I"] = attitude(args.attitude_runs, args.attitude_duration)
    if not args.skip_marg:
        result["marg_broad"] = marg()
    if not args.skip_geo:
        for label, rows in geo(args.geo_duration).items():
            result[f"geo_{label}"] = rows
    if not args.skip_square_root:
        from symkf.scenarios.toolchain import square_root_float
        result["launcher_square_root"] = square_root_float.launcher(args.square_root_runs)
        if not args.skip_attitude:
            result["attitude_square_root"] = square_root_float.attitude(args.attitude_runs, args.attitude_duration)
        if not args.skip_geo:
            for label, rows in square_root_float.geo(args.geo_duration, GEO_RUNS).items():
                result[f"geo_square_root_{label}"] = rows
        if args.model:
            result["model_square_root"] = square_root_float.user_model(args.model)
    emit(result, args.out, args.json, _print)
    return 0


#: (section, metric, unit) of the printed table.
_METRICS = {"launcher_20Hz_small": ("r_rms_m", "m"), "attitude_scenario_I": ("attitude_rms_deg", "deg"),
            "marg_broad": ("mean_total_rmse_deg", "deg"),
            **{f"geo_{label}": ("attitude_estimation_rms_deg", "deg") for label in GEO_RUNS}}


def _print(result: dict) -> None:
    print(f"{'case':20s} {'filter':9s} {'metric':34s} {'double':>9s} {'float':>9s} {'ratio':>6s} {'refused d/f':>11s}")
    for section, (metric, unit) in _METRICS.items():
        for family, rows in result.get(section, {}).items():
            if family == "skipped":
                print(f"{section:20s} skipped: {rows}")
                continue
            d, f = rows["double"], rows["float"]
            refused = f"{d['refused_steps']}/{f['refused_steps']}"
            if metric not in d or metric not in f:
                print(f"{section:20s} {family:9s} refused: {d.get('refused', '-')} / {f.get('refused', '-')}")
                continue
            diverged = f"  diverged runs {d['diverged_runs']}/{f['diverged_runs']}" if "diverged_runs" in d else ""
            print(f"{section:20s} {family:9s} {metric + ' (' + unit + ')':34s} {d[metric]:9.4g} {f[metric]:9.4g} "
                  f"{f[metric] / d[metric]:6.2f} {refused:>11s}{diverged}")
    _print_square_root(result)


#: (section, metric, unit) of the square-root rows; every build beside double.
_SQUARE_ROOT_METRICS = {"launcher_square_root": ("r_rms_m", "m"), "attitude_square_root": ("attitude_rms_deg", "deg"),
                        **{f"geo_square_root_{label}": ("attitude_estimation_rms_deg", "deg") for label in GEO_RUNS},
                        "model_square_root": ("position_rms_m", "m")}


def _print_square_root(result: dict) -> None:
    for section, (metric, unit) in _SQUARE_ROOT_METRICS.items():
        for family, rows in result.get(section, {}).items():
            d = rows["double"]
            for build, row in rows.items():
                if build == "double":
                    continue
                value = f"{row[metric]:9.4g} {row[metric] / d[metric]:6.2f}" if metric in row else "  refused       "
                print(f"{section:20s} {family:9s} {metric + ' (' + unit + ') ' + build:34s} {d[metric]:9.4g} {value} "
                      f"{str(d['refused_steps']) + '/' + str(row['refused_steps']):>11s}")

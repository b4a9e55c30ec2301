"""The series of ``symkf compare geo`` (paper 003, Table 7, Figs 12-21), saved as ``series.nc``
(:mod:`symkf.scenarios.results`), and the figures redrawn from it by ``symkf plot <folder>``.

One row of dimension ``run`` per closed loop of every case run (its case, name, estimator and
failed gyros beside it); per run and 1/8 s tick (``step``, NaN past the run's ``steps``: a run
that diverged stops early): the truth, the estimate and the EKF's sigma = sqrt(diag P) of the 17
states of ``models/geo_satellite.py`` (units per state in ``state_units``) and the wheel and body
torques, so that a loaded run is a ``LoopResult`` again; per run: its status (converged / bounded
/ diverged, ``compare.classify``) and peak and final attitude error.
"""
from __future__ import annotations

from pathlib import Path

from symkf.models import geo_satellite as geo
from symkf.scenarios import results as R
from .closed_loop import LoopResult, LoopSettings
from .figures import plot_case

STATUSES = ("converged", "bounded", "diverged")
#: units of each block of the state (the model's paper units: in-lbf-s for wheel momentum)
BLOCK_UNITS = {"integral": "rad s", "angle": "rad", "rate": "rad/s", "momentum": "in-lbf-s", "bias": "rad/s"}


def state_units() -> list[str]:
    units = [""] * len(geo.STATE_NAMES)
    for block, where in geo.SLICES.items():
        units[where] = [BLOCK_UNITS[block]] * len(units[where])
    return units


def make_series(cases: dict[int, dict], metrics: dict[int, dict], attrs: dict) -> R.Series:
    """``cases``: {case: {run name: LoopResult}}; ``metrics``: {case: {run name: run_metrics}}."""
    names = [(case, name) for case, runs in cases.items() for name in runs]
    loops = [cases[c][n] for c, n in names]
    t, steps = R.padded([r.t for r in loops])
    padded = {k: R.padded([getattr(r, k) for r in loops])[0]
              for k in ("truth", "estimate", "sigma", "wheel_torque", "body_torque")}
    status = [STATUSES.index(metrics[c][n]["status"]) for c, n in names]
    v = {
        "run": R.var(["run"], [f"case{c} {n}" for c, n in names], long_name="case and run name"),
        "state": R.var(["state"], list(geo.STATE_NAMES), long_name="state of models/geo_satellite.py"),
        "state_units": R.var(["state"], state_units()),
        "run_case": R.var(["run"], [c for c, _ in names], "1", "Table 7 case"),
        "run_name": R.var(["run"], [n for _, n in names]),
        "run_estimator": R.var(["run"], [r.settings.estimator for r in loops], long_name="ekf or sensors (no EKF)"),
        "run_failed_gyros": R.var(["run"], ["".join(r.settings.failed_gyros) for r in loops]),
        "run_bias": R.var(["run"], [r.settings.bias for r in loops], "1", "gyro bias on"),
        "run_noise": R.var(["run"], [r.settings.noise for r in loops], "1", "sensor noise on"),
        "run_initial": R.var(["run"], [r.settings.initial for r in loops], long_name="initial errors: Table 6 or 4"),
        "steps": R.var(["run"], steps, "1", "ticks of the run"),
        "time": R.var(["run", "step"], t, "s", "time (1/8 s ticks; NaN past steps)"),
        "truth": R.var(["run", "step", "state"], padded["truth"], "see state_units", "true state"),
        "estimate": R.var(["run", "step", "state"], padded["estimate"], "see state_units",
                          "estimate (NaN where the estimator has no such quantity)"),
        "sigma": R.var(["run", "step", "state"], padded["sigma"], "see state_units", "EKF sqrt(diag P) (NaN without EKF)"),
        "wheel_torque": R.var(["run", "step", "wheel"], padded["wheel_torque"], "in-lbf", "commanded wheel torque"),
        "body_torque": R.var(["run", "step", "axis"], padded["body_torque"], "in-lbf", "body torque, eq (5)"),
        "run_status": R.var(["run"], status, "1", "0 converged, 1 bounded, 2 diverged",
                            flag_values=[0, 1, 2], flag_meanings=" ".join(STATUSES)),
        "run_peak_attitude_error": R.var(["run", "axis"], [metrics[c][n]["peak_attitude_error_deg"] for c, n in names],
                                         "deg", "peak |attitude error| per axis"),
        "run_final_attitude_error": R.var(["run", "axis"], [metrics[c][n]["final_attitude_error_deg"] for c, n in names],
                                          "deg", "final |attitude error| per axis"),
    }
    return R.Series("geo", v, attrs)


def loops(series: R.Series) -> dict[int, dict[str, LoopResult]]:
    """{case: {run name: LoopResult}} of a loaded series, in the order they were run."""
    out: dict[int, dict[str, LoopResult]] = {}
    for i, name in enumerate(series.labels("run_name")):
        n = series["steps"][i]
        settings = LoopSettings(float(R.attribute(series, "duration_s")), str(series["run_estimator"][i]),
                                bias=bool(series["run_bias"][i]), noise=bool(series["run_noise"][i]),
                                failed_gyros=tuple(str(series["run_failed_gyros"][i])),
                                initial=str(series["run_initial"][i]))
        history = {k: R.trimmed(series[k][i], n) for k in ("time", "truth", "estimate", "sigma", "wheel_torque",
                                                           "body_torque")}
        out.setdefault(int(series["run_case"][i]), {})[name] = LoopResult(
            settings, history["time"], history["truth"], history["estimate"], history["sigma"],
            history["wheel_torque"], history["body_torque"])
    return out


def redraw(series: R.Series, out: Path) -> list[Path]:
    """case<N>.png of every case in a loaded series."""
    Path(out).mkdir(parents=True, exist_ok=True)
    return [plot_case(case, runs, Path(out)) for case, runs in loops(series).items()]

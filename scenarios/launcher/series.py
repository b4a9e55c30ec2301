"""The series behind the launcher figures (paper 004, Figs 5-6, the NEES, filter vs smoother) and its
per-run rows, saved by ``symkf compare launcher`` as ``series.nc`` (:mod:`symkf.scenarios.results`:
netCDF with dimension names and units; ``series.npz`` without the ``results`` extra), so that
``symkf plot <folder>`` redraws the figures without running a filter (e.g. after a change of style,
or on another machine).

Per case (dimension ``case``; its rate and initial error beside it): the times, the filters' and
smoothers' RMS(t) over the runs in Table 3's units (eq (8); ``rms``, dims case x estimate x step x
state, NaN past a case's ``steps``), their whole-flight RMS (eq (11)), the average NEES over the
runs with its stride and 95 % band; per run (dimension ``run``): outcome (ok / diverged /
excursion), failed steps, mean NEES, whole-run RMS and final error per state. Global attributes:
the figures' configuration line, preset, runs, seed.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from symkf.models import launcher as L
from symkf.scenarios import results as R
from .campaign import ANGLE_STATES, ESTIMATES, FILTERS, PER_RUN_COLUMNS, STATE_NAMES, CaseResult, consistency

OUTCOMES = ("ok", "diverged", "excursion")


@dataclass
class SavedNees:
    """The average NEES of one filter over the runs, as ``ErrorAccumulator`` gives it to the figures."""

    nees: np.ndarray
    nees_stride: int

    def mean_nees(self) -> np.ndarray:
        return self.nees


@dataclass
class SavedCase:
    """One case's saved series, read by scenarios/launcher/figures.py as a ``CaseResult``."""

    case: SimpleNamespace          # label, rate_hz, initial_error
    times: np.ndarray
    rms: dict[str, np.ndarray]
    whole: dict[str, np.ndarray]
    errors: dict[str, SavedNees]
    nees_band_95: list[float]

    def rms_in_table_units(self, family: str) -> np.ndarray:
        return self.rms[family]

    def whole_flight(self, family: str) -> np.ndarray:
        return self.whole[family]


def make_series(results: list[CaseResult], config: str, attrs: dict | None = None) -> R.Series:
    """The :class:`~symkf.scenarios.results.Series` of a campaign's results."""
    units = list(L.TABLE3_UNITS)
    times, steps = R.padded([r.times for r in results])
    rms = np.stack([R.padded([r.rms_in_table_units(f) for r in results])[0] for f in ESTIMATES], axis=1)
    nees, nees_steps = R.padded([np.stack([r.errors[f].mean_nees() for f in FILTERS], axis=1) for r in results])
    runs = [_per_run(r) for r in results]
    v = {
        "case": R.var(["case"], [r.case.label for r in results], long_name="radar rate and initial error"),
        "estimate": R.var(["estimate"], list(ESTIMATES), long_name="filter, or filter + fixed-interval RTS smoother"),
        "filter": R.var(["filter"], list(FILTERS)),
        "state": R.var(["state"], list(STATE_NAMES), long_name="state of Table 3"),
        "state_units": R.var(["state"], units, long_name="units of each state's errors (Table 3)"),
        "outcome": R.var(["outcome"], list(OUTCOMES)),
        "run": R.var(["run"], np.arange(len(runs[0]["failed"][0])), "1", "Monte Carlo run index"),
        "bound": R.var(["bound"], ["low", "high"]),
        "rate_hz": R.var(["case"], [r.case.rate_hz for r in results], "Hz", "radar rate"),
        "initial_error": R.var(["case"], [r.case.initial_error for r in results],
                               long_name="initial error: small eq (9) or large eq (10)"),
        "steps": R.var(["case"], steps, "1", "time steps of the case (rows of time and rms)"),
        "time": R.var(["case", "step"], times, "s", "time since lift-off (NaN past steps)"),
        "rms": R.var(["case", "estimate", "step", "state"], rms, "see state_units",
                     "RMS error over the runs at each time, eq (8)"),
        "rms_whole_flight": R.var(["case", "estimate", "state"],
                                  [[r.whole_flight(f) for f in ESTIMATES] for r in results], "see state_units",
                                  "whole-flight RMS error, eq (11)"),
        "nees_steps": R.var(["case"], nees_steps, "1", "NEES samples of the case"),
        "nees_stride": R.var(["case", "filter"], [[r.errors[f].nees_stride for f in FILTERS] for r in results],
                             "1", "time steps between NEES samples"),
        "nees": R.var(["case", "nees_step", "filter"], nees, "1", "average NEES over the runs (6 states)"),
        "nees_band_95": R.var(["case", "bound"], [consistency(r, "ekf")["nees_band_95"] for r in results], "1",
                              "95 % chi-square band of the average NEES over the runs"),
        "run_outcome": R.var(["case", "estimate", "run"], np.stack([r["outcome"] for r in runs]), "1",
                             "0 ok, 1 diverged, 2 excursion (campaign.outcome)",
                             flag_values=[0, 1, 2], flag_meanings=" ".join(OUTCOMES)),
        "run_failed_steps": R.var(["case", "estimate", "run"], np.stack([r["failed"] for r in runs]), "1",
                                  "steps the filter refused in the run"),
        "run_mean_nees": R.var(["case", "estimate", "run"], np.stack([r["nees"] for r in runs]), "1",
                               "mean NEES of the run"),
        "run_rms": R.var(["case", "estimate", "run", "state"], np.stack([r["rms"] for r in runs]), "see state_units",
                         "RMS error of the run over the flight"),
        "run_final_error": R.var(["case", "estimate", "run", "state"], np.stack([r["final"] for r in runs]),
                                 "see state_units", "error of the run at the last time"),
    }
    return R.Series("launcher", v, {"config": config, **(attrs or {})})


def _per_run(result: CaseResult) -> dict[str, np.ndarray]:
    """One case's per-run rows, by estimate, angles in degrees as in Table 3."""
    column = {name: i for i, name in enumerate(PER_RUN_COLUMNS)}
    rows = [result.per_run(f) for f in ESTIMATES]
    first = column["mean_sq_error_" + STATE_NAMES[0]]
    final = column["final_error_" + STATE_NAMES[0]]
    degrees = np.where(ANGLE_STATES, 180 / np.pi, 1.0)
    return {"outcome": np.stack([row[:, column["diverged"]] + 2 * row[:, column["excursion"]] for row in rows]).astype(int),
            "failed": np.stack([row[:, column["failed_steps"]] for row in rows]).astype(int),
            "nees": np.stack([row[:, column["mean_nees"]] for row in rows]),
            "rms": np.stack([np.sqrt(row[:, first:first + 6]) * degrees for row in rows]),
            "final": np.stack([row[:, final:final + 6] * degrees for row in rows])}


def save(results: list[CaseResult], folder: Path, config: str, attrs: dict | None = None) -> Path:
    """Write the series file of ``folder`` from a campaign's results."""
    return R.save(make_series(results, config, attrs), folder)


def load(folder: Path) -> tuple[list[SavedCase], str]:
    """The saved cases of ``folder`` and the figures' configuration line."""
    return cases(R.load(folder))


def cases(series: R.Series) -> tuple[list[SavedCase], str]:
    """The figures' cases of a loaded launcher series, and its configuration line."""
    if series.comparison != "launcher":
        raise ValueError(f"a '{series.comparison}' series, not the launcher's")
    estimates, filters = series.labels("estimate"), series.labels("filter")
    out = []
    for i, label in enumerate(series.labels("case")):
        case = SimpleNamespace(label=label, rate_hz=int(series["rate_hz"][i]),
                               initial_error=str(series["initial_error"][i]))
        steps, nees_steps = series["steps"][i], series["nees_steps"][i]
        out.append(SavedCase(
            case, R.trimmed(series["time"][i], steps),
            {f: R.trimmed(series["rms"][i, k], steps) for k, f in enumerate(estimates)},
            {f: series["rms_whole_flight"][i, k] for k, f in enumerate(estimates)},
            {f: SavedNees(R.trimmed(series["nees"][i, :, k], nees_steps), int(series["nees_stride"][i, k]))
             for k, f in enumerate(filters)},
            [float(v) for v in series["nees_band_95"][i]]))
    return out, str(series.attrs["config"])


def redraw(series: R.Series, out: Path) -> list[Path]:
    """The launcher figures of a loaded series, into ``out``."""
    from . import figures
    results, config = cases(series)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths = [out / "fig_velocity_rms.png", out / "fig_radius_rms.png", out / "fig_nees.png", out / "fig_smoother_rms.png"]
    figures.plot_rms(results, "V", "Speed error RMS (m/s)", paths[0], config)
    figures.plot_rms(results, "r", "Radius error RMS (m)", paths[1], config)
    figures.plot_nees(results, paths[2], config)
    figures.plot_smoother_rms(results, "V", "Speed error RMS (m/s)", paths[3], config)
    return paths

"""The series of ``symkf compare attitude`` (paper 000, Figs 1-4) and its per-run rows, saved as
``series.nc`` (:mod:`symkf.scenarios.results`), and its two figures drawn from them, so that
``symkf plot <folder>`` redraws them without running a filter.

Per filter (MEKF, UKF) and gyro time: the RMS over the runs of the attitude error angle (deg) and
of the gyro-bias error norm (rad/s), and run 1's own curves (the figures' thin lines); per run:
RMS attitude error over the last half (deg), the per-axis mean-square error there, failed steps,
converged (the summary's definition, ``compare.CONVERGED_RMS_DEG``).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from symkf.models import attitude as att
from symkf.scenarios import results as R

FILTERS = ("mekf", "ukf")
LABELS = {"mekf": "Kalman filter (MEKF)", "ukf": "proposed UKF"}


def make_series(data: dict, scenario: str, converged: dict[str, np.ndarray], attrs: dict) -> R.Series:
    """The series of one campaign (``compare.campaign``'s data; ``converged``: per filter, per run)."""
    half = data["half"]
    stack = lambda key, f: np.stack([f(data[key][name]) for name in FILTERS])      # noqa: E731
    rms = lambda values: np.sqrt(np.mean(values ** 2, axis=0))                     # noqa: E731
    v = {
        "filter": R.var(["filter"], list(FILTERS)),
        "time": R.var(["time"], data["times"], "s", "time at the end of each gyro interval"),
        "run": R.var(["run"], np.arange(len(data["failed"]["mekf"])), "1", "Monte Carlo run index"),
        "axis": R.var(["axis"], ["x", "y", "z"], long_name="body axis"),
        "attitude_error_rms": R.var(["filter", "time"], stack("angle", rms), "deg",
                                    "RMS over the runs of the attitude error angle"),
        "bias_error_rms": R.var(["filter", "time"], stack("bias", rms), "rad/s",
                                "RMS over the runs of the gyro-bias error norm"),
        "attitude_error_run1": R.var(["filter", "time"], stack("angle", lambda v: v[0]), "deg",
                                     "attitude error angle of run 1"),
        "bias_error_run1": R.var(["filter", "time"], stack("bias", lambda v: v[0]), "rad/s",
                                 "gyro-bias error norm of run 1"),
        "run_attitude_rms": R.var(["filter", "run"], stack("angle", lambda v: np.sqrt(np.mean(v[:, half:] ** 2, axis=1))),
                                  "deg", "RMS attitude error of the run over the last half"),
        "run_axis_mean_square": R.var(["filter", "run", "axis"], stack("axis_sq", lambda v: v), "deg2",
                                      "mean-square error rotation per axis over the last half"),
        "run_failed_steps": R.var(["filter", "run"], stack("failed", lambda v: v), "1", "steps the filter refused"),
        "run_converged": R.var(["filter", "run"], np.stack([converged[f] for f in FILTERS]), "1",
                               "no failed step and last-half RMS below the convergence threshold"),
    }
    return R.Series("attitude", v, {"scenario": scenario, **attrs})


def redraw(series: R.Series, out: Path) -> list[Path]:
    """fig_attitude_error.png and fig_bias_error.png from a loaded series."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    filters, times, runs = series.labels("filter"), series["time"], len(series["run"])
    paths = []
    for key, filename, ylabel, scale in (("attitude", "fig_attitude_error.png", "attitude error norm [deg]", 1.0),
                                         ("bias", "fig_bias_error.png", "gyro bias error norm [deg/h]",
                                          np.rad2deg(1) * 3600)):
        fig, ax = plt.subplots(figsize=(7, 4))
        for i, name in enumerate(filters):
            color = "C0" if name == "mekf" else "C1"
            ax.semilogy(times, series[f"{key}_error_run1"][i] * scale, lw=0.4, alpha=0.4, color=color)
            ax.semilogy(times, series[f"{key}_error_rms"][i] * scale, lw=1.4, ls="-" if name == "mekf" else "--",
                        color=color, label=f"{LABELS[name]}, RMS over runs")
        if key == "attitude":
            ax.axhline(att.ATTITUDE_REQUIREMENT_3SIGMA_DEG, color="k", ls="--", lw=0.8, label="0.025° requirement")
        ax.set_xlabel("time [s]")
        ax.set_ylabel(ylabel)
        ax.set_title(f"Paper 000 scenario {series.attrs['scenario']} ({runs} runs; thin: run 1)")
        ax.grid(True, which="both", lw=0.3)
        ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(out / filename, dpi=130)
        plt.close(fig)
        paths.append(out / filename)
    return paths

"""The series of ``symkf compare marg`` on one recording (paper 001, Fig 3), saved as ``series.nc``
(:mod:`symkf.scenarios.results`), and its figures redrawn from it by ``symkf plot <folder>``.

Per gain β and sample: the Euler angles (5) of the estimate (rad; ``angle``: psi, theta, phi) and,
when the recording has one, of the optical reference (NaN where markers were lost); the sample
times; global attributes: the recording, form, mode, the zoom window and (with ``--sweep``) the
sweep's rows as JSON, from which the sweep figure is drawn.
"""
from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np

from symkf.scenarios import results as R
from .figures import plot_euler, plot_sweep

ANGLES = ("psi", "theta", "phi")


def make_series(recording, per_beta: list[tuple[float, np.ndarray]], reference: np.ndarray | None,
                args, sweep: dict | None) -> R.Series:
    v = {
        "beta": R.var(["beta"], [beta for beta, _ in per_beta], "rad/s", "filter gain"),
        "angle": R.var(["angle"], list(ANGLES), long_name="Euler angles (5): yaw, pitch, roll"),
        "time": R.var(["time"], recording.time, "s", "sample time of the recording"),
        "euler": R.var(["beta", "time", "angle"], np.stack([a for _, a in per_beta]), "rad",
                       "Euler angles (5) of the estimate"),
    }
    if reference is not None:
        v["reference_euler"] = R.var(["time", "angle"], reference, "rad",
                                     "Euler angles (5) of the optical reference (NaN: markers lost)")
    attrs = {"recording": recording.name, "form": args.form, "mode": args.mode, "zoom_s": list(args.zoom)}
    if sweep is not None:
        attrs["sweep"] = sweep
    return R.Series("marg", v, attrs)


def redraw(series: R.Series, out: Path) -> list[Path]:
    """The Euler-angle figures (whole and zoomed) and, if saved, the sweep figure (none for a
    folder of trials: its result is the table)."""
    if series.attrs.get("kind") == "trials":
        return []
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    name, form, mode = series.attrs["recording"], series.attrs["form"], series.attrs["mode"]
    recording = SimpleNamespace(name=name, time=series["time"])
    per_beta = [(float(beta), series["euler"][i]) for i, beta in enumerate(series["beta"])]
    reference = series["reference_euler"] if "reference_euler" in series.variables else None
    paths = [out / f"euler_{name}_{form}_{mode}.png", out / f"euler_zoom_{name}_{form}_{mode}.png"]
    plot_euler(recording, per_beta, reference, paths[0])
    plot_euler(recording, per_beta, reference, paths[1], window=tuple(R.attribute(series, "zoom_s")))
    if "sweep" in series.attrs:
        paths.append(out / f"sweep_{name}_{form}_{mode}.png")
        plot_sweep(R.attribute(series, "sweep"), paths[-1], name)
    return paths


# ---------------------------------------------------------------------- a folder of BROAD trials
METRICS = ("total", "heading", "inclination")


def trials_series(rows: list[dict], filters: tuple[str, ...], attrs: dict) -> R.Series:
    """The per-trial rows of ``symkf compare marg --data DIR``: BROAD RMSE per trial, filter and metric."""
    v = {
        "trial": R.var(["trial"], [r["trial"] for r in rows]),
        "filter": R.var(["filter"], list(filters), long_name="Madgwick at 0.041, at its best beta, MEKF, MEKF + RTS"),
        "metric": R.var(["metric"], list(METRICS), long_name="BROAD error metric over movement phases"),
        "rmse": R.var(["trial", "filter", "metric"], [[[r[f][m] for m in METRICS] for f in filters] for r in rows],
                      "deg", "BROAD RMSE"),
        "samples": R.var(["trial"], [r["samples"] for r in rows], "1", "IMU samples of the trial"),
        "best_beta": R.var(["trial"], [r["best_beta"] for r in rows], "rad/s", "Madgwick's best beta (an oracle)"),
        "mekf_failed_steps": R.var(["trial"], [r["mekf_failed_steps"] for r in rows], "1"),
        "mekf_gated_steps": R.var(["trial"], [r["mekf_gated_steps"] for r in rows], "1"),
        "mekf_heading_used_fraction": R.var(["trial"], [r["mekf_heading_used_fraction"] for r in rows], "1",
                                            "fraction of samples whose magnetometer heading the MEKF used"),
        "mekf_rts_failed_steps": R.var(["trial"], [r["mekf_rts_failed_steps"] for r in rows], "1",
                                       "steps refused in the smoother's offline forward pass"),
        "axis": R.var(["axis"], ["x", "y", "z"]),
        "mekf_rts_gyro_scale_error": R.var(["trial", "axis"], [r["mekf_rts_gyro_scale_error_percent"] for r in rows],
                                           "%", "gyro scale-factor error estimated by the smoother, at the start"),
    }
    return R.Series("marg", v, {"kind": "trials", **attrs})

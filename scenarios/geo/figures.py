"""The figure of each ``symkf compare geo`` case (paper 003, Table 7, Figs 12-21): attitude and
integrated angle per axis (no EKF), or their largest axis and the EKF's estimation errors (log),
one line per run of the case. Drawn from the runs (``LoopResult``) or from the saved series
(scenarios/geo/series.py): the same PNG.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from symkf.models import geo_satellite as geo


def plot_case(case: int, results: dict, out: Path) -> Path:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ekf = any(r.settings.estimator != "sensors" for r in results.values())
    rows = ["attitude", "integral"] + (["angle", "rate", "momentum", "bias"] if ekf else [])
    fig, axes = plt.subplots(len(rows), 3 if not ekf else 1, figsize=(13, 2.6 * len(rows)), squeeze=False)
    for name, r in results.items():
        series = {"attitude": (r.attitude_deg, "attitude (deg)"),
                  "integral": (np.rad2deg(r.truth[:, geo.SLICES["integral"]]), "integrated angle (deg s)")}
        if ekf:
            series.update({"angle": (np.rad2deg(r.estimation_error("angle")), "angle est. error (deg)"),
                           "rate": (np.rad2deg(r.estimation_error("rate")), "rate est. error (deg/s)"),
                           "momentum": (r.estimation_error("momentum"), "momentum est. error (in-lbf-s)"),
                           "bias": (np.rad2deg(r.estimation_error("bias")), "bias est. error (deg/s)")})
        for i, row in enumerate(rows):
            data, label = series[row]
            if ekf:
                axes[i, 0].plot(r.t, np.max(np.abs(data), axis=1), label=name, lw=0.8)
                axes[i, 0].set_yscale("log")
                axes[i, 0].set_ylabel("max |" + label + "|", fontsize=8)
            else:
                for j in range(3):
                    axes[i, j].plot(r.t, data[:, j], label=name, lw=0.8)
                    axes[i, j].set_title(f"{label}, axis {'xyz'[j]}", fontsize=8)
    for ax in axes[-1]:
        ax.set_xlabel("time (s)")
    axes[0, 0].legend(fontsize=6, ncol=2)
    fig.suptitle(f"Paper 003, Table 7 case {case}")
    fig.tight_layout()
    path = out / f"case{case}.png"
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path

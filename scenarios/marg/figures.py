"""The figures of ``symkf compare marg`` (paper 001, Fig 3): Euler angles (5) per gain β with the
optical reference, whole and zoomed, and the β sweep (BROAD RMSE and oscillation vs β). Drawn
from the saved series (scenarios/marg/series.py), by the compare and by ``symkf plot`` alike.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .data import Recording

ANGLE_NAMES = ("psi (yaw)", "theta (pitch)", "phi (roll)")


def plot_euler(recording: Recording, per_beta: list[tuple[float, np.ndarray]], reference: np.ndarray | None,
               path: Path, window: tuple[float, float] | None = None) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(3, len(per_beta), figsize=(5.5 * len(per_beta), 7), sharex=True, squeeze=False)
    t = recording.time - recording.time[0]
    shown = slice(None) if window is None else (t >= window[0]) & (t <= window[1])
    t = t[shown]
    for col, (beta, angles) in enumerate(per_beta):
        for row in range(3):
            ax = axes[row, col]
            if reference is not None:
                ax.plot(t, np.degrees(reference[shown, row]), color="0.6", lw=0.8, label="optical reference")
            ax.plot(t, np.degrees(angles[shown, row]), lw=0.6, label=f"estimate, beta = {beta:g}")
            ax.set_ylabel(f"{ANGLE_NAMES[row]} [deg]")
            if row == 0:
                ax.set_title(f"beta = {beta:g} rad/s")
                ax.legend(loc="upper right", fontsize=7)
        axes[2, col].set_xlabel("time [s]")
    span = "" if window is None else f", {window[0]:g}-{window[1]:g} s"
    fig.suptitle(f"Euler angles (5), {recording.name}{span} (cf. paper 001 Fig 3)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_sweep(result: dict, path: Path, name: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    betas = np.array(result["betas"])
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4))
    if "best_beta" in result:
        for key in ("total", "heading", "inclination"):
            ax1.semilogx(betas, [r["broad_rmse_deg"][key] for r in result["rows"]], marker=".", label=key)
        ax1.axvline(result["best_beta"], color="k", ls="--", lw=0.8, label=f"best beta = {result['best_beta']:g}")
        ax1.set_ylabel("BROAD RMSE [deg]")
        ax1.legend()
    ax1.set_xlabel("beta [rad/s]")
    ax1.set_title(name)
    osc = [r["oscillation"] for r in result["rows"]]
    if "error_hf_rms_deg" in osc[0]:        # motion removed: oscillation about the reference, and at rest
        ax2.loglog(betas, [o["error_hf_rms_deg"] for o in osc], marker=".", label="error HF RMS [deg]")
        ax2.loglog(betas, [np.linalg.norm(o["still_diff_rms_deg"]) for o in osc], marker=".",
                   label="still-phase diff RMS [deg/sample]")
    else:
        hf = np.array([o["hf_rms_deg"] for o in osc])
        for j in range(3):
            ax2.loglog(betas, hf[:, j], marker=".", label=f"{ANGLE_NAMES[j]} HF RMS [deg]")
    ax2.set_title("oscillation measures")
    ax2.set_xlabel("beta [rad/s]")
    ax2.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)

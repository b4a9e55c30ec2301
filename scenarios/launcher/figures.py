"""The figures of ``symkf compare launcher`` (paper 004, Figs 5-6 and the NEES), drawn for a report.

One panel per case (radar rate x initial error), both filters in each:

- the UKF is a wide, light solid line and the EKF a dark dashed line with markers drawn *on top*
  of it, so the EKF stays visible where the two coincide; a panel where they agree within 2 %
  everywhere says so in its title;
- the paper's whole-flight RMS (Table 3, eq (11): one number per filter and case, the paper's
  figures themselves are not available) is drawn as a dotted horizontal line per filter beside our
  RMS(t), labelled "paper Table 3", and each panel prints both filters' whole-flight RMS, ours and
  the paper's;
- the event lines (staging, second-stage ignition, radar hand-over) and the NEES band are keyed in
  one legend below the panels, outside the data;
- the title names the filter configuration, the number of runs and the seed.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from symkf.models import launcher as L
from .campaign import STATE_NAMES, CaseResult, consistency

EVENT_LINES = ((L.T_STAGE1_BURNOUT, "staging"), (L.T_STAGE2_IGNITION, "2nd ignition"),
               (L.RADAR_HANDOVER_TIMES[0], "hand-over"), (L.RADAR_HANDOVER_TIMES[1], "hand-over"))
#: How each filter is drawn: the UKF first (wide, light), the EKF over it (dashed, markers).
STYLE = {"ukf": dict(color="tab:orange", lw=2.6, ls="-", alpha=0.75, zorder=2),
         "ekf": dict(color="tab:blue", lw=1.0, ls="--", marker="o", ms=3, zorder=3)}
EVENT_STYLE = {"staging / 2nd ignition": dict(color="0.45", lw=0.9, ls="-"),
               "radar hand-over": dict(color="0.45", lw=0.9, ls=":")}
#: Curves closer than this (relative, at every time) are said to coincide.
COINCIDE = 0.02


def _pyplot():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def _panels(plt, results: list[CaseResult]):
    rates = sorted({r.case.rate_hz for r in results}, reverse=True)
    fig, axes = plt.subplots(len(rates), 2, figsize=(12, 3.6 * len(rates) + 1.4), squeeze=False, sharex=True)
    placed = {}
    for result in results:
        col = 0 if result.case.initial_error == "small" else 1
        placed[result.case.label] = axes[rates.index(result.case.rate_hz), col]
    return fig, axes, placed


def _mark_events(ax, duration: float) -> None:
    for t, label in EVENT_LINES:
        if t <= duration:
            key = "radar hand-over" if label == "hand-over" else "staging / 2nd ignition"
            ax.axvline(t, label=key, **EVENT_STYLE[key])


def _curves(ax, times: np.ndarray, series: dict[str, np.ndarray], title: str) -> None:
    """Both filters' curves, the UKF under the EKF; the panel's title says when they coincide."""
    for family in ("ukf", "ekf"):
        ax.semilogy(times, series[family], label=family.upper(), markevery=max(1, len(times) // 25),
                    **STYLE[family])
    if _coincide(series["ekf"], series["ukf"]):
        title += f" (EKF and UKF coincide within {COINCIDE:.0%})"
    ax.set_title(title, fontsize=10)


def _coincide(a: np.ndarray, b: np.ndarray) -> bool:
    return bool(np.all(np.abs(a - b) <= COINCIDE * np.maximum(np.abs(b), 1e-300)))


def _finish(plt, fig, axes, title: str, path: Path) -> None:
    for ax in axes[-1]:
        ax.set_xlabel("time since lift-off (s)")
    handles, labels = {}, []
    for ax in axes.ravel():
        for handle, label in zip(*ax.get_legend_handles_labels()):
            if label not in handles:
                handles[label] = handle
                labels.append(label)
    fig.suptitle(title, fontsize=11)
    fig.legend([handles[k] for k in labels], labels, loc="lower center", ncol=min(len(labels), 6), frameon=False,
               fontsize=9)
    fig.tight_layout(rect=(0, 0.06, 1, 0.97))
    fig.savefig(path, dpi=110)
    plt.close(fig)


def configuration(preset: str, runs: int, seed: int) -> str:
    """The configuration line of every figure's title."""
    return f"filters '{preset}', {runs} Monte Carlo runs per case, seed {seed}"


def plot_rms(results: list[CaseResult], state: str, ylabel: str, path: Path, config: str) -> None:
    """RMS(t) of one state over the runs (eq (8)), ours beside the paper's whole-flight value."""
    index = STATE_NAMES.index(state)
    plt = _pyplot()
    fig, axes, placed = _panels(plt, results)
    for result in results:
        ax = placed[result.case.label]
        _curves(ax, result.times, {f: result.rms_in_table_units(f)[:, index] for f in ("ekf", "ukf")},
                f"{result.case.label} initial error")
        paper = dict(zip(("ekf", "ukf"), L.TABLE3[(result.case.rate_hz, result.case.initial_error)][state]))
        for family in ("ukf", "ekf"):
            ax.axhline(paper[family], color=STYLE[family]["color"], lw=1.2, ls=(0, (1, 2)),
                       label=f"paper Table 3, {family.upper()} (whole-flight RMS)", zorder=1)
        ours = {family: result.whole_flight(family)[index] for family in ("ekf", "ukf")}
        ax.text(0.98, 0.96, f"whole-flight RMS, eq (11): ours EKF {ours['ekf']:.3g}, UKF {ours['ukf']:.3g}\n"
                f"paper EKF {paper['ekf']:.3g}, UKF {paper['ukf']:.3g}", transform=ax.transAxes, ha="right",
                va="top", fontsize=8, color="0.2", bbox=dict(facecolor="white", edgecolor="0.8", alpha=0.85))
        _mark_events(ax, result.times[-1])
        ax.set_ylabel(ylabel)
    _finish(plt, fig, axes, f"Paper 004 launcher: {ylabel.split(' (')[0]}, ours vs paper — {config}", path)


def plot_nees(results: list[CaseResult], path: Path, config: str) -> None:
    """The average NEES over the runs (6 states) against its 95 % chi-square band."""
    plt = _pyplot()
    fig, axes, placed = _panels(plt, results)
    for result in results:
        ax = placed[result.case.label]
        stride = result.errors["ekf"].nees_stride
        _curves(ax, result.times[::stride], {f: result.errors[f].mean_nees() for f in ("ekf", "ukf")},
                f"{result.case.label} initial error")
        low, high = getattr(result, "nees_band_95", None) or consistency(result, "ekf")["nees_band_95"]
        ax.axhspan(low, high, color="tab:green", alpha=0.18, label="95 % band of the average NEES", zorder=0)
        _mark_events(ax, result.times[-1])
        ax.set_ylabel("average NEES over runs")
    _finish(plt, fig, axes, f"Paper 004 launcher: consistency (NEES, 6 states) — {config}", path)


def plot_smoother_rms(results: list, state: str, ylabel: str, path: Path, config: str) -> None:
    """RMS(t) of one state, each filter (drawn as in the other figures) beside its fixed-interval
    RTS smoothing (thin solid, same colour): what the backward pass buys at every time."""
    index = STATE_NAMES.index(state)
    plt = _pyplot()
    fig, axes, placed = _panels(plt, results)
    for result in results:
        ax = placed[result.case.label]
        for family in ("ukf", "ekf"):
            color = STYLE[family]["color"]
            ax.semilogy(result.times, result.rms_in_table_units(family)[:, index], label=family.upper(),
                        markevery=max(1, len(result.times) // 25), **STYLE[family])
            wide = family == "ukf"                  # as the filters: the UKF's wide and light, under the EKF's
            ax.semilogy(result.times, result.rms_in_table_units(f"{family}_rts")[:, index], ls="-",
                        lw=3.0 if wide else 1.2, color=color, alpha=0.5 if wide else 0.95,
                        label=f"{family.upper()} + RTS smoother", zorder=4 if wide else 5)
        title = f"{result.case.label} initial error"
        if _coincide(result.rms_in_table_units("ekf_rts")[:, index], result.rms_in_table_units("ukf_rts")[:, index]):
            title += f" (the two smoothers coincide within {COINCIDE:.0%})"
        ax.set_title(title, fontsize=10)
        _mark_events(ax, result.times[-1])
        ax.set_ylabel(ylabel)
    _finish(plt, fig, axes, f"Paper 004 launcher: {ylabel.split(' (')[0]}, filter vs RTS smoother — {config}", path)

"""The series behind the launcher figures (paper 004, Figs 5-6, the NEES, filter vs smoother), saved as
``series.npz`` by ``symkf compare launcher``, so that ``symkf plot <folder>`` redraws the three
figures from them without running a filter (e.g. after a change of style, or on another machine).

Per case: the times, both filters' and smoothers' RMS(t) in Table 3's units (eq (8)), their whole-flight RMS
(eq (11)), the average NEES over the runs with its stride and 95 % band; and the title line of
the figures (configuration, runs, seed).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from .campaign import ESTIMATES, FILTERS, CaseResult, consistency

SERIES_FILE = "series.npz"


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


def save(results: list[CaseResult], folder: Path, config: str) -> Path:
    """Write ``folder/series.npz`` from a campaign's results."""
    arrays = {"config": np.array(config), "labels": np.array([r.case.label for r in results])}
    for i, r in enumerate(results):
        arrays[f"{i}_case"] = np.array([r.case.rate_hz, 0 if r.case.initial_error == "small" else 1])
        arrays[f"{i}_times"] = r.times
        arrays[f"{i}_band"] = np.array(consistency(r, "ekf")["nees_band_95"])
        for f in ESTIMATES:                          # the filters and their smoothers
            arrays[f"{i}_{f}_rms"] = r.rms_in_table_units(f)
            arrays[f"{i}_{f}_whole"] = r.whole_flight(f)
        for f in FILTERS:
            arrays[f"{i}_{f}_nees"] = r.errors[f].mean_nees()
            arrays[f"{i}_{f}_stride"] = np.array(r.errors[f].nees_stride)
    path = Path(folder) / SERIES_FILE
    np.savez_compressed(path, **arrays)
    return path


def load(folder: Path) -> tuple[list[SavedCase], str]:
    """The saved cases of ``folder`` and the figures' configuration line; FileNotFoundError names
    the file and how to make it."""
    path = Path(folder) / SERIES_FILE
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no saved series; `symkf compare launcher --out {folder}` writes it")
    with np.load(path, allow_pickle=False) as data:
        cases = [_case(data, i, str(label)) for i, label in enumerate(data["labels"])]
        return cases, str(data["config"])


def _case(data, i: int, label: str) -> SavedCase:
    rate, error = (int(v) for v in data[f"{i}_case"])
    case = SimpleNamespace(label=label, rate_hz=rate, initial_error=("small", "large")[error])
    return SavedCase(case, data[f"{i}_times"], {f: data[f"{i}_{f}_rms"] for f in ESTIMATES},
                     {f: data[f"{i}_{f}_whole"] for f in ESTIMATES},
                     {f: SavedNees(data[f"{i}_{f}_nees"], int(data[f"{i}_{f}_stride"])) for f in FILTERS},
                     [float(v) for v in data[f"{i}_band"]])


def redraw(folder: Path, out: Path | None = None) -> list[Path]:
    """The launcher figures of ``folder``'s saved series, into ``out`` (default: ``folder``)."""
    from . import figures
    results, config = load(folder)
    out = Path(folder) if out is None else Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths = [out / "fig_velocity_rms.png", out / "fig_radius_rms.png", out / "fig_nees.png", out / "fig_smoother_rms.png"]
    figures.plot_rms(results, "V", "Speed error RMS (m/s)", paths[0], config)
    figures.plot_rms(results, "r", "Radius error RMS (m)", paths[1], config)
    figures.plot_nees(results, paths[2], config)
    figures.plot_smoother_rms(results, "V", "Speed error RMS (m/s)", paths[3], config)
    return paths

"""``symkf plot <folder>``: redraw a saved comparison's figures from its series file alone.

Each ``symkf compare`` saves its series (:mod:`symkf.scenarios.results`) with its own name as the
file's ``comparison`` attribute; the module named here for it draws the figures from the loaded
series, as the comparison drew them (the same PNG), without building a model or running a filter.
A folder whose sub-folders hold series (``results/attitude/scenario_I``) is redrawn sub-folder by
sub-folder.
"""
from __future__ import annotations

import importlib
from pathlib import Path

from symkf.scenarios import results as R

#: The module whose ``redraw(series, out) -> [paths]`` draws each comparison's figures.
REDRAW = {"launcher": "symkf.scenarios.launcher.series", "attitude": "symkf.scenarios.attitude.series",
          "geo": "symkf.scenarios.geo.series", "marg": "symkf.scenarios.marg.series"}


def redraw(folder: Path, out: Path | None = None) -> list[Path]:
    """Every figure of the saved comparisons in ``folder`` (and its sub-folders), into ``out``
    (default: beside each series file; with sub-folders, ``out/<sub-folder>``)."""
    folder = Path(folder)
    found = R.folders_with_series(folder)
    if not found:
        raise FileNotFoundError(f"{folder}: no saved series ({R.NETCDF_FILE} or {R.NPZ_FILE}) here or one "
                                "folder down; `symkf compare <name> --out FOLDER` writes one")
    paths = []
    for where in found:
        series = R.load(where)
        if series.comparison not in REDRAW:
            raise ValueError(f"{where}: a series of '{series.comparison}', which symkf plot does not know")
        target = where if out is None else Path(out) / where.relative_to(folder)
        paths += importlib.import_module(REDRAW[series.comparison]).redraw(series, target)
    return paths

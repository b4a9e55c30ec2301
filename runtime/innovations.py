"""The innovations of a run, step by step: y, S and the normalised innovation squared (NIS).

NIS_k = y_k^T S_k^-1 y_k (Bar-Shalom, Li & Kirubarajan 2001, sec. 5.4): for a consistent filter it
is chi-square distributed with as many degrees of freedom as step k used measurement components
(a masked component has y = 0 and an identity row in S, so it adds nothing and counts nothing).
The run loop keeps y and S per step (the generated ``_run_diag``); a step that failed gets NaN.
Time and Monte-Carlo averages with their chi-square bands are in ``symkf.scenarios.consistency``.
"""
from __future__ import annotations

import numpy as np

from symkf.codegen.spec import STATUS_GATED, STATUS_OK


class Innovations:
    """y, S, nis and nis_dof of a run (:class:`~symkf.runtime.runs.RunResult`), computed on first
    use from its ``innovations`` (the run loop's histories) and ``status``: a run that never reads
    them pays only the loop's y and S rows."""

    @property
    def y(self):
        """Each step's innovation (N, m); NaN for a failed step; None if the run kept none."""
        return self._innovation("y")

    @property
    def S(self):
        """Each step's innovation covariance (N, m, m)."""
        return self._innovation("S")

    @property
    def nis(self):
        """Each step's normalised innovation squared y^T S^-1 y (N,)."""
        return self._innovation("nis")

    @property
    def nis_dof(self):
        """The degrees of freedom of each step's NIS (the measurement components it used)."""
        return self._innovation("nis_dof")

    def _innovation(self, key: str):
        if "_innovations" not in self.__dict__:
            self.__dict__["_innovations"] = of_run(self.innovations.get("kept", {}), self.innovations.get("mask"),
                                                   self.status)
        return self.__dict__["_innovations"].get(key)


def of_run(kept: dict[str, np.ndarray], mask: np.ndarray | None, status: np.ndarray) -> dict:
    """RunResult's y, S, nis and nis_dof from a run loop's histories ``kept`` (y rows, S rows
    column-major), the run's per-step ``mask`` and ``status``; {} if the loop kept no y and S."""
    if "y" not in kept or "S" not in kept:
        return {}
    y = np.asarray(kept["y"], dtype=float).reshape(len(status), -1).copy()
    m = y.shape[1]
    S = np.asarray(kept["S"], dtype=float).reshape(len(status), m, m).transpose(0, 2, 1).copy()
    failed = (status != STATUS_OK) & (status != STATUS_GATED)
    y[failed], S[failed] = np.nan, np.nan
    return {"y": y, "S": S, "nis": nis(y, S), "nis_dof": degrees_of_freedom(mask, y.shape)}


def nis(y: np.ndarray, S: np.ndarray) -> np.ndarray:
    """y_k^T S_k^-1 y_k per step (N,), for y (N, m) and S (N, m, m); NaN where y or S is."""
    value = np.full(len(y), np.nan)
    ok = np.isfinite(y).all(axis=1) & np.isfinite(S).all(axis=(1, 2))
    if ok.any():
        solved = np.linalg.solve(S[ok], y[ok][..., None])[..., 0]
        value[ok] = np.einsum("ki,ki->k", y[ok], solved)
    return value


def degrees_of_freedom(mask: np.ndarray | None, shape: tuple[int, int]) -> np.ndarray:
    """The used innovation components per step: the mask's count, or all m of a quaternion
    measurement's 3-vector innovation when its one mask entry is set."""
    n_steps, m = shape
    if mask is None:
        return np.full(n_steps, m)
    used = np.asarray(mask).reshape(n_steps, -1) > 0.5
    return used.sum(axis=1) if used.shape[1] == m else used[:, 0] * m

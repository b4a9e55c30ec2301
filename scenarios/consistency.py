"""Filter consistency from NEES and NIS series, with their chi-square bands: the one place for them.

For a consistent filter, NEES_k = e_k^T P_k^-1 e_k (e = truth - estimate) is chi-square with n
degrees of freedom and NIS_k = y_k^T S_k^-1 y_k with as many as the components used at step k
(Bar-Shalom, Li & Kirubarajan 2001, sec. 5.4). Averages of independent values are tested against
the band of chi2(sum of dof) / count:

- :func:`time_average`: one run, averaged over its steps (dof summed over the steps);
- :func:`monte_carlo_average`: per step, averaged over runs (dof summed over the runs);
- :func:`chi2_band`: the two-sided band of such an average.

A run's NIS comes from the run itself (``RunResult.nis``, ``nis_dof``: symkf.runtime.innovations);
its NEES from :func:`nees_series` given the truth. Steps without a value (NaN: failed, or NIS of
a step with no measurement used) are left out of every average and its degrees of freedom.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from symkf.scenarios.metrics import nees, state_error


@dataclass(frozen=True)
class Average:
    """An average of chi-square values, its expected value and its two-sided band."""

    value: float | np.ndarray
    expected: float | np.ndarray      # mean dof per value
    low: float | np.ndarray
    high: float | np.ndarray
    probability: float

    @property
    def inside(self):
        """True where the average lies in its band (a consistent filter: ``probability`` of the time)."""
        return (self.value >= self.low) & (self.value <= self.high)


def chi2_band(dof_total, count, probability: float = 0.95):
    """Two-sided band of the average of ``count`` independent chi-square values whose degrees of
    freedom add up to ``dof_total``: chi2.ppf(tails, dof_total) / count (arrays broadcast)."""
    from scipy.stats import chi2       # here, not at import: a campaign's workers never need it
    tail = (1 - probability) / 2
    count = np.maximum(count, 1)
    return chi2.ppf(tail, dof_total) / count, chi2.ppf(1 - tail, dof_total) / count


def time_average(values, dof, probability: float = 0.95) -> Average:
    """One run's series (N,) with per-step degrees of freedom (N,) or a scalar, averaged over time."""
    values = np.asarray(values, dtype=float)
    dof = np.broadcast_to(np.asarray(dof, dtype=float), values.shape)
    used = np.isfinite(values) & (dof > 0)
    count = int(np.count_nonzero(used))
    low, high = chi2_band(dof[used].sum(), count, probability)
    mean = float(values[used].mean()) if count else np.nan
    return Average(mean, float(dof[used].mean()) if count else np.nan, float(low), float(high), probability)


def monte_carlo_average(values, dof, probability: float = 0.95) -> Average:
    """Series of R runs (R, N) with degrees of freedom (R, N), (N,) or a scalar, averaged over the
    runs at each step: arrays (N,) of averages, expected values and band limits."""
    values = np.asarray(values, dtype=float)
    if values.ndim != 2:
        raise ValueError(f"monte_carlo_average: expected (runs, steps) values, got shape {values.shape}")
    dof = np.broadcast_to(np.asarray(dof, dtype=float), values.shape)
    used = np.isfinite(values) & (dof > 0)
    count = used.sum(axis=0)
    total = np.where(used, dof, 0.0).sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(count > 0, np.where(used, values, 0.0).sum(axis=0) / count, np.nan)
        expected = np.where(count > 0, total / count, np.nan)
    low, high = chi2_band(total, count, probability)
    return Average(mean, expected, np.where(count > 0, low, np.nan), np.where(count > 0, high, np.nan), probability)


def nees_series(truth, estimate, covariance, angles=None) -> np.ndarray:
    """NEES per step (N,) of a run given the truth (N, n); ``angles`` flags wrapped states."""
    truth = np.asarray(truth, dtype=float)
    flags = np.zeros(truth.shape[-1], bool) if angles is None else angles
    return nees(state_error(truth, estimate, flags), np.asarray(covariance, dtype=float))

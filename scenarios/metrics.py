"""Monte Carlo metrics: RMS error per time (paper 004 eq (8)), its whole-flight mean (eq (11)),
and the normalised estimation error squared (NEES) with its chi-square consistency band.

Accumulators keep running sums so a campaign never holds every run's history in memory.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.stats import chi2


@dataclass
class ErrorAccumulator:
    """Sums over Monte Carlo runs of squared errors and NEES, per time step."""

    n_steps: int
    n_states: int
    nees_stride: int = 1
    runs: int = 0
    squared_error: np.ndarray = field(init=False)
    nees: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        self.squared_error = np.zeros((self.n_steps, self.n_states))
        self.nees = np.zeros(len(range(0, self.n_steps, self.nees_stride)))

    def add(self, truth: np.ndarray, estimate: np.ndarray, covariance: np.ndarray) -> None:
        """One run: truth and estimate (n_steps, n), covariance (n_steps, n, n)."""
        error = truth - estimate
        stride = self.nees_stride
        self.add_run(error**2, nees(error[::stride], covariance[::stride]))

    def add_run(self, squared_error: np.ndarray, nees_values: np.ndarray) -> None:
        """One run's squared errors (n_steps, n) and NEES on every nees_stride-th step."""
        self.squared_error += squared_error
        self.nees += nees_values
        self.runs += 1

    def rms(self) -> np.ndarray:
        """Eq (8): epsilon_i(k) = sqrt(mean over runs of error^2), shape (n_steps, n)."""
        return np.sqrt(self.squared_error / max(self.runs, 1))

    def mean_nees(self) -> np.ndarray:
        """Run-averaged NEES on the decimated grid (steps 0, stride, 2 stride, ...)."""
        return self.nees / max(self.runs, 1)


def nees(error: np.ndarray, covariance: np.ndarray) -> np.ndarray:
    """e^T P^-1 e per time step, scaled by the standard deviations first (P spans 1e-16..1e6)."""
    sigma = np.sqrt(np.einsum("kii->ki", covariance))
    scaled_error = error / sigma
    correlation = covariance / (sigma[:, :, None] * sigma[:, None, :])
    return np.einsum("ki,ki->k", scaled_error, np.linalg.solve(correlation, scaled_error[..., None])[..., 0])


def whole_flight_mean(rms: np.ndarray) -> np.ndarray:
    """Eq (11): a_i = (1/k) sum_j epsilon_i(j), the mean of the RMS over all observation times."""
    return rms.mean(axis=0)


def nees_band(n_states: int, runs: int, probability: float = 0.95) -> tuple[float, float]:
    """Two-sided band for the run-averaged NEES of a consistent filter: chi2(runs * n) / runs."""
    tail = (1 - probability) / 2
    dof = runs * n_states
    return chi2.ppf(tail, dof) / runs, chi2.ppf(1 - tail, dof) / runs

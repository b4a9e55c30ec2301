"""Monte Carlo metrics: RMS error per time (paper 004 eq (8)), its whole-flight mean (eq (11)),
and the normalised estimation error squared (NEES); its chi-square bands are in consistency.py.

Every metric starts from :func:`state_error`, which wraps angle components to (-pi, pi]: an
estimate 360 deg off in a flight-path angle has *converged*, and its error is 0, not 2 pi.

Accumulators keep running sums so a campaign never holds every run's history in memory.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from symkf.runtime.reference import wrap_angle


def state_error(truth: np.ndarray, estimate: np.ndarray, angles) -> np.ndarray:
    """truth - estimate, with the components flagged in ``angles`` (a boolean per state, last
    axis) wrapped to (-pi, pi]; the one place metrics turn two states into an error."""
    error = np.asarray(truth, dtype=float) - np.asarray(estimate, dtype=float)
    angles = np.asarray(angles, dtype=bool)
    if angles.shape != error.shape[-1:]:
        raise ValueError(f"angles: expected {error.shape[-1]} flags (one per state), got shape {angles.shape}")
    return np.where(angles, wrap_angle(error), error)


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

    def add(self, truth: np.ndarray, estimate: np.ndarray, covariance: np.ndarray, angles=None) -> None:
        """One run: truth and estimate (n_steps, n), covariance (n_steps, n, n); ``angles`` flags
        the states whose error is wrapped (:func:`state_error`)."""
        error = state_error(truth, estimate, np.zeros(self.n_states, bool) if angles is None else angles)
        stride = self.nees_stride
        self.add_run(error**2, nees(error[::stride], covariance[::stride]))

    def add_run(self, squared_error: np.ndarray, nees_values: np.ndarray) -> None:
        """One run's squared errors (n_steps, n) and NEES on every nees_stride-th step."""
        self.squared_error += squared_error
        self.nees += nees_values
        self.runs += 1

    def merge(self, other: "ErrorAccumulator") -> None:
        """Add another accumulator's sums (e.g. a campaign task's runs) to these."""
        if (other.n_steps, other.n_states, other.nees_stride) != (self.n_steps, self.n_states, self.nees_stride):
            raise ValueError("merge: accumulators of different shapes")
        self.squared_error += other.squared_error
        self.nees += other.nees
        self.runs += other.runs

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

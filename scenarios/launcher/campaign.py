"""KSLV-I EKF-vs-UKF Monte Carlo campaign (paper 004, section 4), the whole run in C.

For each case (radar rate x initial error) and each Monte Carlo run: radar noise is drawn once
and fed to *both* filters; each filter runs the whole flight in one call of the generated
``<filter>_step_radar_run`` loop (C, GIL released), and runs are spread over all cores with
threads. Errors are accumulated on the fly (eq (8), eq (11), NEES).

Filter tuning (ours; the paper gives none), in ``TUNING``:
- x_hat(0) = x(0) - dx0 with dx0 from eq (9) or (10); P0 = diag(sigma0^2) with
  sigma0 = max(|dx0|, floor), floor = [0.01 m/s, 1e-8 rad, 1e-8 rad, 0.1 m, 1e-9 rad, 1e-9 rad]
  (a zero initial variance would make the filter ignore the data).
- Q: the filters know the thrust program (a known input) so the model error is the RK4 step
  across staging and ignition; Q = diag(0.005 (m/s)^2/s, 1e-12, 1e-12 rad^2/s, 0.005 m^2/s,
  1e-16, 1e-16 rad^2/s), discrete Q dt (chosen from 5e-4..0.5 on 3-run trials: smaller Q
  lowers the steady-state RMS, larger Q recovers faster from the staging steps).
- R = diag(sigma_R^2, sigma_E^2, sigma_A^2) of section 3.2; UKF kappa = 0 (weights 1/2n).
"""
from __future__ import annotations

import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from symkf.models import launcher as L
from symkf.runtime import load
from .truth import propagate, radar_track
from symkf.scenarios.metrics import ErrorAccumulator, nees, nees_band, state_error, whole_flight_mean

STATE_NAMES = ("V", "gamma", "psi", "r", "theta", "phi")
ANGLE_STATES = np.array([False, True, True, False, True, True])
TUNING = {
    "P0_floor": np.array([0.01, 1e-8, 1e-8, 0.1, 1e-9, 1e-9]),
    "Q": np.diag([0.005, 1e-12, 1e-12, 0.005, 1e-16, 1e-16]),
    "kappa": 0.0,
}
FILTERS = ("ekf", "ukf")
NEES_STRIDE = 5          # NEES every 5th step (0.25 s at 20 Hz): plotted, not tabulated
EXCURSION_ANGLE_RAD = 0.1   # an angle error above 0.1 rad (5.7 deg) at any time: an excursion
DIVERGED_ANGLE_RAD = 0.01   # still above 0.01 rad in the second half of the flight: diverged


def outcome(error: np.ndarray) -> str:
    """'diverged', 'excursion' (a large transient that recovered) or 'ok' for one run's errors
    (wrapped: see :func:`~symkf.scenarios.metrics.state_error`)."""
    angles = np.abs(error[:, ANGLE_STATES])
    if angles[len(angles) // 2:].max() > DIVERGED_ANGLE_RAD:
        return "diverged"
    return "excursion" if angles.max() > EXCURSION_ANGLE_RAD else "ok"


@dataclass(frozen=True)
class Case:
    rate_hz: int
    initial_error: str           # "small" (eq 9) or "large" (eq 10)

    @property
    def label(self) -> str:
        return f"{self.rate_hz}Hz {self.initial_error}"


@dataclass
class CaseResult:
    """Accumulated metrics of one case for both filters."""

    case: Case
    times: np.ndarray
    errors: dict[str, ErrorAccumulator]
    wall_s: dict[str, float] = field(default_factory=dict)
    failed_steps: dict[str, int] = field(default_factory=dict)
    diverged_runs: dict[str, list[int]] = field(default_factory=dict)
    excursion_runs: dict[str, list[int]] = field(default_factory=dict)
    #: the same metrics over the runs that did not diverge (None if none diverged)
    errors_converged: dict[str, ErrorAccumulator] = field(default_factory=dict)

    @classmethod
    def empty(cls, case: Case, times: np.ndarray) -> "CaseResult":
        def accumulators():
            return {f: ErrorAccumulator(len(times), 6, NEES_STRIDE) for f in FILTERS}
        return cls(case, times, accumulators(), {f: 0.0 for f in FILTERS}, {f: 0 for f in FILTERS},
                   {f: [] for f in FILTERS}, {f: [] for f in FILTERS}, accumulators())

    def rms_in_table_units(self, family: str, converged_only: bool = False) -> np.ndarray:
        """RMS per time, angles converted to degrees (Table 3's units)."""
        rms = (self.errors_converged if converged_only else self.errors)[family].rms()
        return np.where(ANGLE_STATES, np.degrees(rms), rms)

    def whole_flight(self, family: str, converged_only: bool = False) -> np.ndarray:
        return whole_flight_mean(self.rms_in_table_units(family, converged_only))


def initial_estimate(case: Case, truth0: np.ndarray, floor=TUNING["P0_floor"]) -> tuple[np.ndarray, np.ndarray]:
    dx0 = np.array(L.INITIAL_ERROR[case.initial_error])
    sigma0 = np.maximum(np.abs(dx0), floor)
    return truth0 - dx0, np.diag(sigma0**2)


def flight_times(rate_hz: int, duration: float) -> np.ndarray:
    return np.arange(int(round(duration * rate_hz)) + 1) / rate_hz


class Campaign:
    """Runs the cases; ``progress(done, total)`` is called after every Monte Carlo run."""

    def __init__(self, runs: int, seed: int, rates=L.RADAR_RATES_HZ, duration: float = L.T_INSERTION,
                 workers: int | None = None, progress=None, tuning: dict | None = None):
        self.runs, self.seed, self.duration = runs, seed, duration
        self.cases = [Case(rate, init) for rate in rates for init in ("small", "large")]
        self.workers = workers or os.cpu_count() or 1
        self.progress = progress or (lambda done, total: None)
        self.model = load("launcher")
        self.tuning = {**TUNING, **(tuning or {})}

    def run(self) -> list[CaseResult]:
        total, done = len(self.cases) * self.runs, 0
        results = []
        for case in self.cases:
            times = flight_times(case.rate_hz, self.duration)
            truth = propagate(times)
            track = radar_track(times, truth)
            result = CaseResult.empty(case, times)
            with ThreadPoolExecutor(self.workers) as pool:
                jobs = [pool.submit(self._one_run, case, run, truth, track) for run in range(self.runs)]
                for run, job in enumerate(jobs):
                    for family, (squared_error, nees_values, failed, wall, outcome) in job.result().items():
                        result.errors[family].add_run(squared_error, nees_values)
                        result.wall_s[family] += wall
                        result.failed_steps[family] += failed
                        if outcome == "diverged":
                            result.diverged_runs[family].append(run)
                        else:
                            result.errors_converged[family].add_run(squared_error, nees_values)
                        if outcome == "excursion":
                            result.excursion_runs[family].append(run)
                    done += 1
                    self.progress(done, total)
            results.append(result)
        return results

    def measurements(self, case: Case, run: int, track) -> np.ndarray:
        """Radar draws for one run: a function of (seed, case, run) only, shared by both filters
        (and the same whichever other cases a campaign includes)."""
        init = ("small", "large").index(case.initial_error)
        return track.noisy(np.random.default_rng([self.seed, case.rate_hz, init, run]))

    def _one_run(self, case: Case, run: int, truth, track) -> dict:
        z = self.measurements(case, run, track)
        q = track.station_params()
        x0, P0 = initial_estimate(case, truth[0], self.tuning["P0_floor"])
        outputs = {}
        for family in FILTERS:
            f = self.model.filter(family, x0, P0, self.tuning["Q"], kappa=self.tuning["kappa"])
            start = time.perf_counter()
            result = f.run(track.times, z, q=q)
            wall = time.perf_counter() - start
            error = state_error(truth, result.x, ANGLE_STATES)
            outputs[family] = (error**2, nees(error[::NEES_STRIDE], result.P[::NEES_STRIDE]),
                               int(np.count_nonzero(result.status)), wall, outcome(error))
        return outputs


def consistency(result: CaseResult, family: str) -> dict:
    """Mean NEES and the fraction of time steps inside the 95 % chi-square band."""
    accumulator = result.errors[family]
    low, high = nees_band(6, accumulator.runs)
    average = accumulator.mean_nees()
    return {"mean_nees": float(np.mean(average)), "nees_band_95": [low, high],
            "fraction_inside_band": float(np.mean((average >= low) & (average <= high)))}

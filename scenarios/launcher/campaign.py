"""KSLV-I EKF-vs-UKF Monte Carlo campaign (paper 004, section 4), the whole run in C.

For each case (radar rate x initial error) and each Monte Carlo run: radar noise is drawn once
and fed to *both* filters; each filter runs the whole flight in the generated C, 4 runs at a
time in AVX2 lanes (``Filter.run_lockstep``: each run's numbers are a run of its own, bit for bit;
GIL released), and tasks are spread over all cores with threads. Errors are accumulated on the
fly (eq (8), eq (11), NEES), for each filter and for its fixed-interval smoothing (``ekf_rts``,
``ukf_rts``: the generated backward pass over the run, 4 at a time too: ``smooth_lockstep``).

Two named filter configurations (``PRESETS``, ``--filters``), each a codegen configuration
(its own library, through ``load("launcher", **overrides)``) plus a tuning; the paper gives none:

- ``correct`` (default): both filters integrate the model with RK4, one step per radar sample,
  split at the model's events (no step straddles staging, fairing, ignition or burnout); the
  EKF's transition matrix is the exact Jacobian of that step. Q comes from the model's
  neglected terms: the filter's model *is* the truth's, so the only model error is the
  discretisation, and Q = 10 x the mean-square one-step defect of the filter's step against the
  CVODES truth, per second (:func:`neglected_terms_q`, the larger of 10 Hz and 20 Hz). P0 =
  diag(max(|dx0|, floor)^2), floor = [1 m/s, 1e-4 rad, 1e-4 rad, 100 m, 1e-5 rad, 1e-5 rad]:
  loose enough that the radar data, not the prior, set the covariance within seconds. The floor
  and the factor 10 were chosen on calibration draws (seed 1, 10 runs) by the fraction of time
  the average NEES lies in its 95 % band; the reported campaign uses seed 2005.
- ``paper-like``: the best-supported reading of what the paper ran (evidence in
  docs/paper004_reproduction.md): EKF = one explicit Euler step per radar sample with
  Phi = I + A dt, UKF = RK4, neither split at events; the earlier tuning Q = diag(0.005 (m/s)^2/s,
  1e-12, 1e-12 rad^2/s, 0.005 m^2/s, 1e-16, 1e-16 rad^2/s) (Q dt per step) and floor
  [0.01 m/s, 1e-8, 1e-8 rad, 0.1 m, 1e-9, 1e-9 rad].

Radar stations: ``correct`` reads section 3.2's coordinates as WGS84 geodetic (measurement
``radar_wgs84``: truth data and filters), ``paper-like`` places them on the spherical Earth
(``radar``, the paper's reading); ``--stations`` overrides either.

Per-filter knobs on top of a preset: ``ekf_q_scale``, ``ukf_q_scale`` (multiply Q for one
filter), ``P0_floor``. x_hat(0) = x(0) - dx0 with dx0 from eq (9) or (10); R = diag(sigma_R^2,
sigma_E^2, sigma_A^2) of section 3.2; UKF kappa = 0 (weights 1/2n).
"""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from symkf.codegen import make_config
from symkf.codegen.c_backend.lockstep import uses_vector_math
from symkf.codegen.model_functions import ModelFunctions
from symkf.models import get_model
from symkf.models import launcher as L
from symkf.runtime import smooth_lockstep
from symkf.scenarios.campaign import ModelKey, Task, chunks, compiled_model, model_key, run_campaign, run_rng
from symkf.scenarios.consistency import chi2_band
from symkf.scenarios.metrics import ErrorAccumulator, nees, state_error, whole_flight_mean
from .truth import propagate, radar_track

STATE_NAMES = ("V", "gamma", "psi", "r", "theta", "phi")
ANGLE_STATES = np.array([False, True, True, False, True, True])
#: 10 x neglected_terms_q(10 Hz) (the larger of 10 and 20 Hz), rounded up: (m/s)^2/s, rad^2/s, m^2/s.
NEGLECTED_TERMS_Q = np.diag([3.4e-14, 1.5e-19, 5.6e-19, 3.2e-10, 9.1e-24, 2.5e-23])
PRESETS = {
    "correct": {
        "codegen": {},
        "tuning": {"P0_floor": np.array([1.0, 1e-4, 1e-4, 100.0, 1e-5, 1e-5]), "Q": NEGLECTED_TERMS_Q,
                   "kappa": 0.0, "ekf_q_scale": 1.0, "ukf_q_scale": 1.0, "stations": "wgs84"}},
    "paper-like": {
        # the UKF's lockstep lanes call libm: libmvec's round-off moves this preset's chaotic 10 Hz
        # large-error UKF runs beyond the Monte Carlo error (theta 4.5 SE, its smoothing's psi 13.7 SE;
        # scenarios/launcher/roundoff_equivalence.py --preset paper-like)
        "codegen": {"ekf_integrator": "euler", "ekf_covariance": "linear", "split_events": False,
                    "ukf_lockstep_vector_math": False},
        "tuning": {"P0_floor": np.array([0.01, 1e-8, 1e-8, 0.1, 1e-9, 1e-9]),
                   "Q": np.diag([0.005, 1e-12, 1e-12, 0.005, 1e-16, 1e-16]),
                   "kappa": 0.0, "ekf_q_scale": 1.0, "ukf_q_scale": 1.0, "stations": "spherical"}},
}
TUNING = PRESETS["correct"]["tuning"]
FILTERS = ("ekf", "ukf")
#: The fixed-interval smoothings of each filter's run (symkf.runtime.smooth: RTS, unscented RTS).
SMOOTHED = ("ekf_rts", "ukf_rts")
ESTIMATES = FILTERS + SMOOTHED
EVENTS = tuple(get_model("launcher").events)     # Table 2's switches (s), declared by the model
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
    #: CPU seconds of the compiled runs (the threads' own CPU time, summed over runs)
    cpu_s: dict[str, float] = field(default_factory=dict)
    failed_steps: dict[str, int] = field(default_factory=dict)
    diverged_runs: dict[str, list[int]] = field(default_factory=dict)
    excursion_runs: dict[str, list[int]] = field(default_factory=dict)
    #: the same metrics over the runs that did not diverge (None if none diverged)
    errors_converged: dict[str, ErrorAccumulator] = field(default_factory=dict)
    #: per-run rows (columns PER_RUN_COLUMNS) in run order, as folded task by task
    per_run_chunks: dict[str, list[np.ndarray]] = field(default_factory=dict)
    #: CPU seconds of the case's tasks in all (the compiled runs and the Python around them)
    task_cpu_s: float = 0.0

    @classmethod
    def empty(cls, case: Case, times: np.ndarray) -> "CaseResult":
        def accumulators():
            return {f: ErrorAccumulator(len(times), 6, NEES_STRIDE) for f in ESTIMATES}
        def per_filter(value):
            return {f: type(value)(value) for f in ESTIMATES}
        return cls(case, times, accumulators(), wall_s=per_filter(0.0), cpu_s=per_filter(0.0), failed_steps=per_filter(0),
                   diverged_runs=per_filter([]), excursion_runs=per_filter([]), errors_converged=accumulators(),
                   per_run_chunks=per_filter([]))

    def add_per_run(self, family: str, rows: np.ndarray) -> None:
        """Fold a task's per-run rows: failed steps, diverged and excursion runs, the rows kept."""
        columns = {name: i for i, name in enumerate(PER_RUN_COLUMNS)}
        self.per_run_chunks[family].append(rows)
        self.failed_steps[family] += int(rows[:, columns["failed_steps"]].sum())
        for kind in ("diverged", "excursion"):
            runs = rows[rows[:, columns[kind]] > 0, columns["run"]].astype(int).tolist()
            getattr(self, f"{kind}_runs")[family].extend(runs)

    def per_run(self, family: str) -> np.ndarray:
        """One row per run (columns PER_RUN_COLUMNS), in run order."""
        return np.vstack([np.zeros((0, len(PER_RUN_COLUMNS))), *self.per_run_chunks[family]])

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


#: Runs per task: fixes how per-run sums are grouped (so totals do not depend on the worker count).
#: A task returns its sums (about 1.7 MB for a whole 20 Hz flight, whatever its run count), so
#: larger tasks ship less per run; 20 keeps 2 workers busy to the end of a 100-run case.
CHUNK_RUNS = 20
#: The campaign's library steps its runs in lockstep, 4 per AVX2 vector, the prediction's sin, cos
#: and exp in glibc's libmvec (codegen options; off in the default build, whose edit loop they
#: would slow): each run differs from one run at a time by libmvec's round-off, Table 3 within its
#: Monte Carlo error (scenarios/launcher/roundoff_equivalence.py).
LOCKSTEP_BUILD = {"ekf_lockstep": True, "ukf_lockstep": True, "ekf_lockstep_vector_math": True,
                  "ukf_lockstep_vector_math": True}
#: The same loops with libm's calls lane by lane (``Campaign(exact=True)``, ``symkf compare launcher
#: --exact``): each run's numbers are one run's at a time (the flight bundle's) bit for bit.
EXACT_LOCKSTEP_BUILD = {"ekf_lockstep": True, "ukf_lockstep": True}
#: Runs a filter and its smoother step at once (Filter.run_lockstep, smooth_lockstep): the
#: histories of 4 runs in memory at once.
LOCKSTEP_RUNS = 4
#: Per-run summary columns (``CaseResult.per_run[family]``, one row per run, in run order).
PER_RUN_COLUMNS = ("run", "failed_steps", "diverged", "excursion", "mean_nees",
                   *(f"mean_sq_error_{s}" for s in STATE_NAMES), *(f"final_error_{s}" for s in STATE_NAMES))


_TRUTH_LOCK = threading.Lock()


def case_flight(rate_hz: int, duration: float, measurement: str = "radar"):
    """(times, truth, radar track) of one radar rate, computed once per process (deterministic).
    Serialised: CasADi's CVODES integrator must not be called from two threads at once."""
    with _TRUTH_LOCK:
        return _case_flight(rate_hz, duration, measurement)


@lru_cache(maxsize=8)
def _case_flight(rate_hz: int, duration: float, measurement: str):
    times = flight_times(rate_hz, duration)
    truth = propagate(times)
    return times, truth, radar_track(times, truth, measurement)


def measurements(seed: int, case: Case, run: int, track) -> np.ndarray:
    """Radar draws for one run: a function of (seed, case, run) only, shared by both filters
    (and the same whichever other cases a campaign includes or wherever the run executes)."""
    init = ("small", "large").index(case.initial_error)
    return track.noisy(run_rng(seed, case.rate_hz, init, run))


@dataclass
class ChunkResult:
    """What one task returns: sums over its runs and one summary row per run (no histories), and
    the wall and CPU seconds spent in the compiled runs (the rest of the task is the Python around them)."""

    errors: dict[str, ErrorAccumulator]
    errors_converged: dict[str, ErrorAccumulator]
    per_run: dict[str, np.ndarray]
    wall_s: dict[str, float]
    cpu_s: dict[str, float] = field(default_factory=lambda: {f: 0.0 for f in ESTIMATES})
    task_cpu_s: float = 0.0          # the whole task's CPU seconds (its thread's)


def make_filter(model, family: str, x0, P0, tuning: dict, t0: float):
    """One filter of the campaign: paper 004 fuses every radar sample (no innovation gate); built
    once per task (1.2 ms each), reset per run."""
    return model.filter(family, x0, P0, tuning["Q"] * tuning[f"{family}_q_scale"], gate="none", t0=t0,
                        **({"kappa": tuning["kappa"]} if family == "ukf" else {}))


def run_chunk(key: ModelKey, case: Case, seed: int, runs: tuple[int, int], duration: float,
              tuning: dict) -> ChunkResult:
    """Runs ``runs[0] .. runs[1] - 1`` of one case through both filters (a campaign task; runs on
    any worker: the model comes from its content hash, the truth is recomputed, the draws are keyed)."""
    task_cpu = time.thread_time()
    model = compiled_model(key)
    measurement = L.RADAR_MEASUREMENTS[tuning["stations"]]
    times, truth, track = case_flight(case.rate_hz, duration, measurement)
    q = track.station_params()
    x0, P0 = initial_estimate(case, truth[0], tuning["P0_floor"])

    def accumulators():
        return {f: ErrorAccumulator(len(times), 6, NEES_STRIDE) for f in ESTIMATES}
    out = ChunkResult(accumulators(), accumulators(), {f: [] for f in ESTIMATES}, {f: 0.0 for f in ESTIMATES})
    filters = {family: make_filter(model, family, x0, P0, tuning, times[0]) for family in FILTERS}
    for group in chunks_of(range(*runs), LOCKSTEP_RUNS):
        z = np.stack([measurements(seed, case, run, track) for run in group])
        for family, f in filters.items():
            start, cpu = time.perf_counter(), time.thread_time()
            results = f.run_lockstep(times, z, measurement, q=q)     # each run from the filter's x0, P0, t0
            out.wall_s[family] += time.perf_counter() - start
            out.cpu_s[family] += time.thread_time() - cpu
            start, cpu = time.perf_counter(), time.thread_time()
            smoothings = smooth_lockstep(f, results, errors="keep")
            out.wall_s[f"{family}_rts"] += time.perf_counter() - start
            out.cpu_s[f"{family}_rts"] += time.thread_time() - cpu
            for run, result, smoothed in zip(group, results, smoothings):
                _add_run(out, family, run, truth, result.x, result.P, np.count_nonzero(result.status))
                _add_run(out, f"{family}_rts", run, truth, smoothed.x_smooth, smoothed.P_smooth,
                         np.count_nonzero(smoothed.smooth_status))
    out.per_run = {f: np.array(rows, dtype=float).reshape(-1, len(PER_RUN_COLUMNS)) for f, rows in out.per_run.items()}
    out.task_cpu_s = time.thread_time() - task_cpu
    return out


def chunks_of(runs: range, size: int) -> list[range]:
    """``runs`` in consecutive ranges of ``size`` (the last may be shorter)."""
    return [runs[i:i + size] for i in range(0, len(runs), size)]


def _add_run(out: ChunkResult, estimate: str, run: int, truth: np.ndarray, x: np.ndarray, P: np.ndarray,
             failed: int) -> None:
    """One run's errors, NEES and summary row of ``estimate`` (a filter or its smoothing)."""
    error = state_error(truth, x, ANGLE_STATES)
    squared, nees_values = error**2, nees(error[::NEES_STRIDE], P[::NEES_STRIDE])
    kind = outcome(error)
    out.errors[estimate].add_run(squared, nees_values)
    if kind != "diverged":
        out.errors_converged[estimate].add_run(squared, nees_values)
    out.per_run[estimate].append([run, failed, kind == "diverged", kind == "excursion", nees_values.mean(),
                                  *squared.mean(axis=0), *error[-1]])


class Campaign:
    """Runs the cases; ``progress(done, total)`` is called as Monte Carlo runs complete.

    ``scheduler``: None (local threads, ``workers`` of them), ``"local:N"`` (a Dask LocalCluster)
    or a Dask scheduler address; see :mod:`symkf.scenarios.campaign`. ``build``: codegen options
    added to the preset's (default none: the model's default build, models/launcher.py). The whole
    library at -O3 (``{"optimization": "-O3 -fno-math-errno"}``, IEEE only, per-run results
    bit-identical, tested) saves under 1 % of the compiled runs' CPU against the default build
    (glue units at -O3, the model's functions at -O1 -fno-thread-jumps) for 4.4 s more compiler CPU
    per cold build: so the default build it is. ``exact``: the lockstep lanes call libm lane by
    lane (:data:`EXACT_LOCKSTEP_BUILD`), so every run is the flight bundle's numbers bit for bit,
    for about 1.5x the CPU; by default they call libmvec (:data:`LOCKSTEP_BUILD`).
    """

    def __init__(self, runs: int, seed: int, rates=L.RADAR_RATES_HZ, duration: float = L.T_INSERTION,
                 workers: int | None = None, progress=None, tuning: dict | None = None,
                 scheduler: str | None = None, preset: str = "correct", chunk_runs: int = CHUNK_RUNS,
                 build: dict | None = None, exact: bool = False):
        if preset not in PRESETS:
            raise ValueError(f"preset: expected one of {sorted(PRESETS)}, got '{preset}'")
        self.runs, self.seed, self.duration, self.preset = runs, seed, duration, preset
        self.chunk_runs = chunk_runs
        self.cases = [Case(rate, init) for rate in rates for init in ("small", "large")]
        self.workers, self.scheduler = workers, scheduler
        self.progress = progress or (lambda done, total: None)
        lockstep = EXACT_LOCKSTEP_BUILD if exact else LOCKSTEP_BUILD
        self.codegen = {**lockstep, **PRESETS[preset]["codegen"], **(build or {})}
        self.model_key = model_key("launcher", **self.codegen)     # one library per configuration
        self.tuning = {**PRESETS[preset]["tuning"], **(tuning or {})}
        self.stats = None

    def arithmetic(self) -> str:
        """How this campaign's library computes, in a line for its tables: which filters' lockstep
        lanes call libmvec (round-off within the Monte Carlo error) or that every run is exact."""
        config = make_config("launcher", **self.codegen)
        vector = [f.upper() for f in FILTERS if uses_vector_math(config, f)]
        if not vector:
            return "every run the flight bundle's numbers bit for bit (libm)"
        return (f"{' and '.join(vector)} runs in lockstep with libmvec in the prediction (round-off, within the "
                "Monte Carlo error; --exact: the flight bundle's numbers bit for bit)")

    def tasks(self) -> list[Task]:
        """The chunks of every case, the longest cases first (a run's cost grows with the radar
        rate), so that the workers' last tasks are the short ones. Each case's chunks stay in run
        order: its sums are folded in the same order whatever the case order."""
        longest_first = sorted(self.cases, key=lambda case: -case.rate_hz)
        return [Task(f"{case.rate_hz}Hz-{case.initial_error}-{r.start}", run_chunk,
                     (self.model_key, case, self.seed, (r.start, r.stop), self.duration, self.tuning), len(r))
                for case in longest_first for r in chunks(self.runs, self.chunk_runs)]

    def run(self, executor=None) -> list[CaseResult]:
        results = {case: CaseResult.empty(case, flight_times(case.rate_hz, self.duration)) for case in self.cases}

        def fold(task: Task, chunk: ChunkResult) -> None:
            result = results[task.args[1]]
            for family in ESTIMATES:
                result.errors[family].merge(chunk.errors[family])
                result.errors_converged[family].merge(chunk.errors_converged[family])
                result.wall_s[family] += chunk.wall_s[family]
                result.cpu_s[family] += chunk.cpu_s[family]
                result.add_per_run(family, chunk.per_run[family])
            result.task_cpu_s += chunk.task_cpu_s
        self.stats = run_campaign(self.tasks(), fold, self.scheduler, self.workers, self.progress, executor)
        return list(results.values())

    def measurements(self, case: Case, run: int, track) -> np.ndarray:
        return measurements(self.seed, case, run, track)


def neglected_terms_q(rate_hz: int, duration: float = L.T_INSERTION, **codegen) -> np.ndarray:
    """The model error a filter makes: the mean-square one-step defect of its discrete step
    f_d(truth_k) - truth_{k+1} against the CVODES truth, per second (a diagonal PSD)."""
    model = get_model("launcher")
    step = ModelFunctions(model, make_config("launcher", **codegen)).fd
    times = flight_times(rate_hz, duration)
    truth = propagate(times)
    n, dt = len(times) - 1, 1.0 / rate_hz
    params = np.tile(np.array(model.param_defaults)[:, None], (1, n))
    predicted = np.array(step.map(n)(times[:-1], np.full(n, dt), truth[:-1].T, np.zeros((0, n)), params)).T
    return np.diag(np.mean((predicted - truth[1:]) ** 2, axis=0) / dt)


#: s: NEES consistency is also reported outside this long a window after each model event
#: (lift-off, staging, fairing, ignition), where the filter is re-converging by design.
EVENT_WINDOW_S = 10.0


def consistency(result: CaseResult, family: str) -> dict:
    """Mean NEES and the fraction of time steps inside the 95 % chi-square band, over the whole
    flight and outside EVENT_WINDOW_S after lift-off and each model event."""
    accumulator = result.errors[family]
    low, high = (float(v) for v in chi2_band(6 * accumulator.runs, accumulator.runs))    # chi2(6 runs) / runs
    average = accumulator.mean_nees()
    inside = (average >= low) & (average <= high)
    times = result.times[::accumulator.nees_stride]
    quiet = ~np.any([(times >= t) & (times < t + EVENT_WINDOW_S) for t in (0.0,) + EVENTS], axis=0)
    return {"mean_nees": float(np.mean(average)), "nees_band_95": [low, high],
            "fraction_inside_band": float(np.mean(inside)),
            "fraction_inside_band_outside_event_windows": float(np.mean(inside[quiet])) if quiet.any() else None,
            "event_window_s": EVENT_WINDOW_S}

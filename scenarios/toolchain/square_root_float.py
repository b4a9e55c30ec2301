"""Float beside double for the EKF, the UKF and their square-root forms (srekf, srukf), on the
launcher with and without its declared scaling and on a user model file with a truth simulation.

Rows of ``symkf bench float`` (:mod:`symkf.scenarios.toolchain.float_bench`):

- launcher (paper 004), the 20 Hz small-error case of the campaign (preset ``correct``, its
  draws): ``runs`` Monte Carlo runs of the whole flight through each filter of each build
  (double; float with the model's declared scales and offsets; float without them,
  ``scaling=False``, as a new user's model would be); whole-flight RMS of r, refused steps and the
  wall seconds of the compiled runs (``filter_seconds``: the square-root forms' cost beside the plain).
- attitude (paper 000, scenario I): the MEKF and the square-root MEKF of the attitude model
  (:func:`attitude_with_square_root`) over ``runs`` runs of ``duration`` s of the scenario's own
  truth and sensors (:mod:`symkf.scenarios.attitude.compare`), double and float: attitude RMS over
  the second half (deg) and refused steps.
- geo (paper 003, Table 7 case 3 with bias and noise, and case 4 with gyros A and C failed): the
  closed loop of :mod:`symkf.scenarios.geo.closed_loop` with the CD-EKF or the square-root CD-EKF
  of :func:`geo_with_square_root` from each build (truth, sensors and controller in double):
  RMS of the attitude estimation error over the second half (deg); a refused update stops the loop.
- a user model file (``--model FILE``): the file's ``build()`` gives the model (its
  ``filters`` name the families compared) and its ``bench_case(rng)`` the record: a dict with
  ``x0, P0, Q, times, z, mask, truth, measurement`` (truth: (N, n), row k the state at times[k]),
  e.g. tests/models/leo_od_model.py. Position error: the first three states, RMS over the second
  half and at the end.

Every filter is built from the same model file by the same generator; the float build differs
only in ``casadi_real``. A step that a filter refuses (status other than 0) keeps its state and
is counted. The launcher's square-root filters come from the model with the two families added
(:func:`launcher_with_square_root`, its own build folder), and so do the attitude and geo ones.
None of these models declares a scaling for its filters' states beyond the launcher's: the
attitude and geo float builds are as a new user's model would be.
"""
from __future__ import annotations

import copy
import runpy
import time

import numpy as np

from symkf.models import get_model
from symkf.models import launcher as L
from symkf.runtime import SymkfError, load
from symkf.scenarios.metrics import state_error

#: The filters compared on the launcher: the model's two and the two square-root forms.
LAUNCHER_FILTERS = ("ekf", "ukf", "srekf", "srukf")
#: The builds compared: (label, codegen overrides).
LAUNCHER_BUILDS = (("double", {}), ("float", {"precision": "float"}),
                   ("float_unscaled", {"precision": "float", "scaling": False}))


def launcher_with_square_root():
    """The launcher model with the square-root families beside its EKF and UKF, named
    ``launcher_sr`` so that its build has its own folder (the equations are the launcher's)."""
    model = copy.copy(get_model("launcher"))
    model.name, model.filters = "launcher_sr", LAUNCHER_FILTERS
    return model


def attitude_with_square_root():
    """The attitude model with the MEKF and the square-root MEKF, named ``attitude_sr``."""
    model = copy.copy(get_model("attitude"))
    model.name, model.filters = "attitude_sr", ATTITUDE_FILTERS
    return model


def geo_with_square_root():
    """The geo model with the CD-EKF and the square-root CD-EKF, named ``geo_sr``."""
    model = copy.copy(get_model("geo_satellite"))
    model.name, model.filters = "geo_sr", GEO_FILTERS
    return model


#: The attitude and geo filters compared: the plain filter and its square-root form.
ATTITUDE_FILTERS = ("mekf", "srmekf")
GEO_FILTERS = ("cd_ekf", "srcdekf")
PRECISION_BUILDS = (("double", {}), ("float", {"precision": "float"}))


def launcher(runs: int, seed: int = 2005) -> dict:
    """{filter: {build: {r_rms_m, V_rms_m_s, refused_steps, runs}}} on the 20 Hz small-error case."""
    from symkf.scenarios.launcher import campaign as C
    case = C.Case(20, "small")
    tuning = C.TUNING
    measurement = L.RADAR_MEASUREMENTS[tuning["stations"]]
    times, truth, track = C.case_flight(case.rate_hz, L.T_INSERTION, measurement)
    x0, P0 = C.initial_estimate(case, truth[0], tuning["P0_floor"])
    draws = [C.measurements(seed, case, run, track) for run in range(runs)]
    out: dict = {}
    for label, overrides in LAUNCHER_BUILDS:
        compiled = load(launcher_with_square_root(), **overrides)
        for family in LAUNCHER_FILTERS:
            base = family[2:] if family.startswith("sr") else family
            f = compiled.filter(family, x0, P0, tuning["Q"] * tuning[f"{base}_q_scale"],
                                **({"kappa": tuning["kappa"]} if base == "ukf" else {}))
            squared, refused, seconds = [], 0, 0.0
            for z in draws:
                f.x, f.P = x0, P0
                f.t = 0.0
                start = time.perf_counter()
                result = f.run(times, z, measurement, q=track.station_params())
                seconds += time.perf_counter() - start
                refused += int(np.count_nonzero(result.status))
                squared.append(state_error(truth, result.x, C.ANGLE_STATES) ** 2)
            rms = np.sqrt(np.mean(squared, axis=0))
            whole = C.whole_flight_mean(np.where(C.ANGLE_STATES, np.degrees(rms), rms))
            out.setdefault(family, {})[label] = {"r_rms_m": float(whole[3]), "V_rms_m_s": float(whole[0]),
                                                 "refused_steps": refused, "runs": runs,
                                                 "filter_seconds": seconds}
    return out


def user_model(path: str, seed: int = 11) -> dict:
    """{filter: {build: {position_rms_m, final_position_error_m, refused_steps, steps}}} for the
    model file ``path`` (module docstring), double and float."""
    case = runpy.run_path(path)["bench_case"](np.random.default_rng(seed))
    model = get_model(path)
    out: dict = {}
    for label, overrides in (("double", {}), ("float", {"precision": "float"})):
        compiled = load(path, **overrides)
        for family in model.filters:
            f = compiled.filter(family, case["x0"], case["P0"], case["Q"])
            f.t = float(case["times"][0])
            try:
                result = f.run(case["times"], case["z"], case["measurement"], mask=case["mask"])
            except SymkfError as exc:             # a run that cannot start (e.g. the first step refused)
                out.setdefault(family, {})[label] = {"refused": str(exc), "refused_steps": len(case["times"])}
                continue
            position = np.linalg.norm(result.x[:, :3] - case["truth"][:, :3], axis=1)
            half = position[position.size // 2:]
            out.setdefault(family, {})[label] = {
                "position_rms_m": float(np.sqrt(np.mean(half ** 2))), "final_position_error_m": float(position[-1]),
                "refused_steps": int(np.count_nonzero(result.status)), "steps": int(position.size)}
    return out


def attitude(runs: int, duration: float, seed: int = 2008) -> dict:
    """{filter: {build: {attitude_rms_deg, refused_steps, runs, duration_s}}}, scenario I."""
    from symkf.models import attitude as att
    from symkf.runtime import Filter
    from symkf.scenarios.attitude import compare as A
    simulator = A._simulator(duration)
    records = []
    for run in range(runs):
        rng = A.run_rng(seed, run)
        record = simulator.simulate(rng, np.full(3, A.SCENARIO_I_BIAS), A.STAR_TRACKER_PERIOD["I"])
        records.append((record, A.initial_estimate(rng, record.q_true0)))
    out: dict = {}
    for label, overrides in PRECISION_BUILDS:
        compiled = load(attitude_with_square_root(), **overrides)
        for family in ATTITUDE_FILTERS:
            squared, refused = [], 0
            for record, q0 in records:
                f = Filter(compiled, family, np.r_[q0, np.zeros(3)], A.P0, att.process_noise_psd(),
                           R={"star_tracker": att.star_tracker_covariance()}, gate="none")
                result = f.run_steps(np.full(len(record.omega_g), A.GYRO_PERIOD), record.star, "star_tracker",
                                     u=record.omega_g, nan="mask", refused="continue")
                refused += int(result.failed_steps.size)
                angle = np.linalg.norm(A.attitude_errors(result.x[:, 0:4], record.q_true), axis=1)
                squared.append(np.rad2deg(angle[angle.size // 2:]) ** 2)
            out.setdefault(family, {})[label] = {"attitude_rms_deg": float(np.sqrt(np.mean(squared))),
                                                 "refused_steps": refused, "runs": runs, "duration_s": duration}
    return out


def geo(duration: float, cases: dict) -> dict:
    """{case: {filter: {build: {attitude_estimation_rms_deg, refused_steps, ...}}}}: the closed loops
    ``cases`` ({label: LoopSettings options}, e.g. ``float_bench.GEO_RUNS``) with each filter from
    each build (truth, sensors, control in double)."""
    double = load("geo_satellite")
    builds = {label: load(geo_with_square_root(), **overrides) for label, overrides in PRECISION_BUILDS}
    out: dict = {}
    for case, options in cases.items():
        for family in GEO_FILTERS:
            for label, compiled in builds.items():
                out.setdefault(case, {}).setdefault(family, {})[label] = geo_loop(double, compiled, family, duration,
                                                                                   options)
    return out


def geo_loop(double, compiled, family: str, duration: float, options: dict) -> dict:
    """One geo closed loop (truth, sensors, control from ``double``) with filter ``family`` of
    ``compiled``: RMS of the attitude estimation error, of the true attitude and of the bias
    estimation error over the second half, or ``refused`` (a refused update stops the loop)."""
    from symkf.scenarios.geo.closed_loop import TICK, ClosedLoop, LoopSettings
    loop = ClosedLoop(LoopSettings(duration, "ekf", bias=True, noise=True, **options), double)
    tuning = loop.tuning
    loop.filter = compiled.filter(family, np.zeros(17), tuning["P0"], tuning["Q"], R=tuning["R"], gate="none")
    try:
        result = loop.run()
    except SymkfError as exc:
        return {"refused": str(exc), "refused_steps": 1}
    half = len(result.t) // 2
    estimation = np.degrees(result.estimation_error("angle")[half:])
    return {"attitude_estimation_rms_deg": float(np.sqrt(np.mean(estimation ** 2))),
            "attitude_rms_deg": float(np.sqrt(np.mean(result.attitude_deg[half:] ** 2))),
            "bias_estimation_rms_rad_s": float(np.sqrt(np.mean(result.estimation_error("bias")[half:] ** 2))),
            "refused_steps": 0, "ticks": len(result.t), "duration_s": duration,
            "completed": bool(len(result.t) == len(np.arange(0.0, duration + 1e-9, TICK)))}

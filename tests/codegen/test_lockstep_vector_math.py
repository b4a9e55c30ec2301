"""Lockstep runs with libmvec (``<family>_lockstep_vector_math``, the launcher campaign's build):
the prediction lanes' sin, cos and exp are glibc's vector calls, so each run differs from
Filter.run by their round-off only; the branch conditions and every step the lanes do not take are the
scalar code's; a run's numbers do not depend on the lane or the group it is stepped in."""
from pathlib import Path

import numpy as np
import pytest

from symkf.codegen import make_config
from symkf.codegen.c_backend import lanes, lockstep, vector_c
from symkf.models import launcher as L
from symkf.runtime import load, smooth, smooth_lockstep
from symkf.scenarios.launcher.campaign import LOCKSTEP_BUILD, TUNING, Case, case_flight, initial_estimate, measurements

AVX2 = "avx2" in Path("/proc/cpuinfo").read_text() if Path("/proc/cpuinfo").exists() else False
pytestmark = pytest.mark.skipif(not AVX2, reason="this CPU has no AVX2: run_lockstep runs each run alone "
                                                 "(the scalar code's numbers, no libmvec)")
MEASUREMENT = "radar_wgs84"
VECTOR_MATH = {"ekf_lockstep_vector_math": True, "ukf_lockstep_vector_math": True}
#: Largest change of any state (or covariance element), in its filter's or smoother's standard
#: deviations, that libmvec's round-off may make over a whole small-error 20 Hz flight (measured
#: over 5 runs: EKF at most 4e-8, UKF 5e-7 filtered and 1.1e-6 smoothed).
ROUND_OFF_SIGMAS = 1e-5


@pytest.fixture(scope="module")
def model():
    assert all(LOCKSTEP_BUILD.get(name) for name in VECTOR_MATH)    # the campaign's build is this one
    return load("launcher", backend="compiled", **LOCKSTEP_BUILD)


@pytest.fixture(scope="module")
def flight():
    return case_flight(20, L.T_INSERTION, MEASUREMENT)


def _filter(model, flight, family):
    times, truth, _ = flight
    x0, P0 = initial_estimate(Case(20, "small"), truth[0], TUNING["P0_floor"])
    return model.filter(family, x0, P0, TUNING["Q"], gate="none", t0=times[0],
                        **({"kappa": 0.0} if family == "ukf" else {}))


def _draws(flight, runs: int) -> np.ndarray:
    return np.stack([measurements(2005, Case(20, "small"), r, flight[2]) for r in range(runs)])


def _alone(f, flight, z, **options):
    """Filter.run of one run from the filter's state (the state restored after it)."""
    times, _, track = flight
    x, P, t = f.x.copy(), f.P.copy(), f.t
    result = f.run(times, z, MEASUREMENT, q=track.station_params(), **options)
    f.x, f.P, f.t = x, P, t
    return result


def _sigmas(a: np.ndarray, b: np.ndarray, P: np.ndarray) -> float:
    """The largest |a - b| over every step and state, in the standard deviations of P."""
    return float(np.max(np.abs(a - b) / np.sqrt(np.diagonal(P, axis1=1, axis2=2))))


def _correlation_change(P: np.ndarray, reference: np.ndarray) -> float:
    """The largest |P - reference| over every step and element, each in sqrt(P_ii P_jj) of the reference."""
    sigma = np.sqrt(np.diagonal(reference, axis1=1, axis2=2))
    return float(np.max(np.abs(P - reference) / (sigma[:, :, None] * sigma[:, None, :])))


def _body(text: str, function: str) -> str:
    """The C body of the generated vector function ``function``."""
    return text.split(f"{function}(const symkf_v4")[1].split("\n}\n")[0]


def test_only_the_prediction_lanes_call_libmvec(model):
    """libmvec in the prediction (the sigma points' f_d) and the smoother's backward step; libm's
    scalar calls lane by lane in the update (h) and in the branch conditions."""
    for family in ("ekf", "ukf"):
        step = (Path(model.build.directory) / f"launcher_{family}_step_{MEASUREMENT}_lockstep.c").read_text()
        prediction = _body(step, f"launcher_{family}_step_{MEASUREMENT}_lanes_predict")
        assert "_ZGVdN4v_sin(" in prediction and "SYMKF_LANE1(sin" not in prediction
        update = _body(step, f"launcher_{family}_step_{MEASUREMENT}_lanes_update")
        assert "_ZGVdN4" not in update and "SYMKF_LANE2(atan2" in update
        assert "_ZGVdN4" not in _body(step, f"launcher_{family}_step_{MEASUREMENT}_flags")
        backward = (Path(model.build.directory) / f"launcher_{family}_smooth_lockstep.c").read_text()
        assert "_ZGVdN4v_sin(" in _body(backward, f"launcher_{family}_smooth_lanes")
    plain = load("launcher", backend="compiled", ekf_lockstep=True)
    text = (Path(plain.build.directory) / f"launcher_ekf_step_{MEASUREMENT}_lockstep.c").read_text()
    assert "_ZGVdN4" not in text                                  # without the option: libm lane by lane


@pytest.mark.parametrize("family", ["ekf", "ukf"])
def test_runs_differ_from_one_by_one_runs_by_round_off_only(model, flight, family):
    times, _, track = flight
    f = _filter(model, flight, family)
    z = _draws(flight, 5)
    results = f.run_lockstep(times, z, MEASUREMENT, q=track.station_params())
    smoothings = smooth_lockstep(f, results, errors="keep")
    for run, result, smoothed in zip(z, results, smoothings):
        alone = _alone(f, flight, run)
        np.testing.assert_array_equal(result.status, alone.status)
        assert 0 < _sigmas(result.x, alone.x, alone.P) < ROUND_OFF_SIGMAS     # not bit-equal: libmvec is used
        assert _correlation_change(result.P, alone.P) < ROUND_OFF_SIGMAS
        reference = smooth(f, alone, errors="keep")
        np.testing.assert_array_equal(smoothed.smooth_status, reference.smooth_status)
        assert _sigmas(smoothed.x_smooth, reference.x_smooth, reference.P_smooth) < ROUND_OFF_SIGMAS


@pytest.mark.parametrize("family", ["ekf", "ukf"])
def test_a_run_is_the_same_in_any_lane_or_group(model, flight, family):
    """Run 2 stepped as lane 2 of a group of 4 and alone (lane 0, the other lanes copies of it):
    the same numbers bit for bit, so a campaign's results do not depend on how it splits its runs."""
    times, _, track = flight
    f = _filter(model, flight, family)
    z = _draws(flight, 4)
    grouped = f.run_lockstep(times, z, MEASUREMENT, q=track.station_params())[2]
    alone = f.run_lockstep(times, z[2:3], MEASUREMENT, q=track.station_params())[0]
    np.testing.assert_array_equal(grouped.x, alone.x)
    np.testing.assert_array_equal(grouped.P, alone.P)
    pair = smooth_lockstep(f, [grouped, alone], errors="keep")
    np.testing.assert_array_equal(pair[0].x_smooth, pair[1].x_smooth)


@pytest.mark.parametrize("family", ["ekf", "ukf"])
def test_refused_and_masked_steps_are_still_the_scalar_steps(model, flight, family):
    """A 1e308 azimuth (an update that overflows) and NaN components masked: the same codes and
    refused steps as Filter.run, and the state around them within round-off."""
    times, _, track = flight
    f = _filter(model, flight, family)
    z = _draws(flight, 3)
    z[1, 300, 1] = 1e308
    z[2, 400:410, 1] = np.nan
    results = f.run_lockstep(times, z, MEASUREMENT, q=track.station_params(), nan="mask", refused="continue")
    for run, result in zip(z, results):
        alone = _alone(f, flight, run, nan="mask", refused="continue")
        np.testing.assert_array_equal(result.status, alone.status)
        np.testing.assert_array_equal(result.refused_steps, alone.refused_steps)
        assert _sigmas(result.x, alone.x, alone.P) < ROUND_OFF_SIGMAS
    assert results[1].refused_steps.tolist() == [300]


def test_without_glibc_s_libmvec_the_lanes_keep_libm(monkeypatch):
    """On a host without glibc's libmvec (macOS, musl, an older glibc) the options leave libm's calls
    lane by lane (the exact loops) instead of failing to link."""
    config = make_config("launcher", **LOCKSTEP_BUILD, ukf_lanes=True)
    assert lockstep.uses_vector_math(config, "ukf") and lanes.enabled(config)
    for libc in (("", ""), ("glibc", "2.31"), ("musl", "1.2")):
        monkeypatch.setattr(vector_c.platform, "libc_ver", lambda libc=libc: libc)
        assert not lockstep.uses_vector_math(config, "ukf") and not lanes.enabled(config)
        assert lockstep.enabled(config, "ukf")                  # the exact lockstep loops stay

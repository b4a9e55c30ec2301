"""Monte Carlo runs in lockstep (codegen/c_backend/lockstep.py, Filter.run_lockstep): the host
library steps 4 runs per AVX2 vector, and each run's result is Filter.run's for that run, bit for
bit: x, P, y, S and every status code, over whole launcher flights that hold the model's events,
refused steps, gated updates and masked measurements."""
import platform
import subprocess
from pathlib import Path

import numpy as np
import pytest

from symkf.codegen import make_config
from symkf.codegen.c_backend import lockstep
from symkf.codegen.compilation import compiler
from symkf.codegen.spec import STATUS_GATED, STATUS_NONFINITE
from symkf.models import launcher as L
from symkf.runtime import RunRefused, load, smooth, smooth_lockstep
from symkf.scenarios.launcher.campaign import TUNING, Case, case_flight, initial_estimate, measurements

AVX2 = "avx2" in Path("/proc/cpuinfo").read_text() if Path("/proc/cpuinfo").exists() else False
MEASUREMENT = "radar_wgs84"
LOCKSTEP = {"ekf_lockstep": True, "ukf_lockstep": True}


@pytest.fixture(scope="module")
def model():
    return load("launcher", backend="compiled", **LOCKSTEP)


@pytest.fixture(scope="module")
def flight():
    times, truth, track = case_flight(20, L.T_INSERTION, MEASUREMENT)
    return times, truth, track


def _filter(model, flight, gate="none", family="ekf", kappa=0.0):
    times, truth, _ = flight
    x0, P0 = initial_estimate(Case(20, "large"), truth[0], TUNING["P0_floor"])
    return model.filter(family, x0, P0, TUNING["Q"], gate=gate, t0=times[0],
                        **({"kappa": kappa} if family == "ukf" else {}))


def _draws(flight, runs: int) -> np.ndarray:
    return np.stack([measurements(2005, Case(20, "large"), r, flight[2]) for r in range(runs)])


def _one_by_one(f, flight, z, **options):
    """Filter.run for each run from the filter's state (the reference)."""
    times, _, track = flight
    x, P, t = f.x.copy(), f.P.copy(), f.t
    out = []
    for run in z:
        f.x, f.P, f.t = x, P, t
        out.append(f.run(times, run, MEASUREMENT, q=track.station_params(), refused="continue", **options))
    f.x, f.P, f.t = x, P, t
    return out


def _assert_same(results, reference):
    assert len(results) == len(reference)
    for a, b in zip(results, reference):
        np.testing.assert_array_equal(a.status, b.status)
        np.testing.assert_array_equal(a.x, b.x)
        np.testing.assert_array_equal(a.P, b.P)
        np.testing.assert_array_equal(a.y, b.y)
        np.testing.assert_array_equal(a.S, b.S)


def _assert_same_smoothing(f, results):
    """smooth_lockstep of the runs equals smooth of each, bit for bit (codes included)."""
    together, alone = smooth_lockstep(f, results, errors="keep"), [smooth(f, r, errors="keep") for r in results]
    for a, b in zip(together, alone):
        np.testing.assert_array_equal(a.smooth_status, b.smooth_status)
        np.testing.assert_array_equal(a.x_smooth, b.x_smooth)
        np.testing.assert_array_equal(a.P_smooth, b.P_smooth)


@pytest.mark.skipif(not AVX2, reason="this CPU has no AVX2: run_lockstep runs each run alone (the same numbers)")
def test_library_has_the_lockstep_loop(model):
    lib = model.backend.lib
    for family in ("ekf", "ukf"):
        assert lib[f"launcher_{family}_step_{MEASUREMENT}_lockstep_available"]() == 1
        assert hasattr(lib, f"launcher_{family}_step_{MEASUREMENT}_run_lockstep")
        assert hasattr(lib, f"launcher_{family}_smooth_run_lockstep")


@pytest.mark.parametrize("family, kappa", [("ekf", 0.0), ("ukf", 0.0), ("ukf", 1.0)])
def test_runs_equal_one_by_one_runs_bit_for_bit(model, flight, family, kappa):
    """7 runs: a full group of 4 and a group of 3 (its fourth lane a copy, not written); the
    flight holds the model's 4 events (the scalar step's split branch). A UKF with kappa = 1 has
    a nonzero centre weight: the lanes hold the centre-free branch, so every step is the scalar one."""
    f = _filter(model, flight, family=family, kappa=kappa)
    z = _draws(flight, 7)
    x, P, t = f.x.copy(), f.P.copy(), f.t
    results = f.run_lockstep(flight[0], z, MEASUREMENT, q=flight[2].station_params())
    np.testing.assert_array_equal(f.x, x)                  # the filter is left as it was
    np.testing.assert_array_equal(f.P, P)
    assert f.t == t
    _assert_same(results, _one_by_one(f, flight, z))
    assert all(r.refused_steps.size == 0 for r in results)
    _assert_same_smoothing(f, results)


@pytest.mark.parametrize("family", ["ekf", "ukf"])
def test_refused_and_masked_steps_are_the_scalar_steps(model, flight, family):
    """A run with a 1e308 azimuth (its update overflows: refused, state kept), one with a 1e308
    range (taken: a finite but absurd state, whose every later step is refused) and one with NaN
    components masked (nan="mask"): each lane the scalar step would not take cleanly is that
    scalar step."""
    f = _filter(model, flight, family=family)
    z = _draws(flight, 5)
    z[1, 300, 1] = 1e308
    z[3, 300, 0] = 1e308
    z[2, 400:410, 1] = np.nan
    results = f.run_lockstep(flight[0], z, MEASUREMENT, q=flight[2].station_params(), nan="mask", refused="continue")
    _assert_same(results, _one_by_one(f, flight, z, nan="mask"))
    _assert_same_smoothing(f, results)                    # refused forward steps: carried smoothed rows
    assert results[1].refused_steps.tolist() == [300] and results[1].status[300] == STATUS_NONFINITE
    assert results[3].refused_steps[0] == 301 and results[3].refused_steps.size == z.shape[1] - 301
    assert np.all(results[2].innovations["mask"][400:410, 1] == 0) and np.all(results[2].y[400:410, 1] == 0)


@pytest.mark.parametrize("family", ["ekf", "ukf"])
def test_gated_updates_are_the_scalar_steps(model, flight, family):
    f = _filter(model, flight, gate={MEASUREMENT: 0.5}, family=family)   # refuses about half the updates
    z = _draws(flight, 5)
    results = f.run_lockstep(flight[0], z, MEASUREMENT, q=flight[2].station_params(), refused="continue")
    _assert_same(results, _one_by_one(f, flight, z))
    assert all(np.count_nonzero(r.status == STATUS_GATED) > 100 for r in results)


def test_a_refused_step_raises_with_the_run_named(model, flight):
    f = _filter(model, flight)
    z = _draws(flight, 3)
    z[2, 50, 0] = 1e308
    with pytest.raises(RunRefused, match=r"run 2\)"):
        f.run_lockstep(flight[0], z, MEASUREMENT, q=flight[2].station_params())


def test_runs_of_different_clocks_are_smoothed_one_by_one(model, flight):
    """smooth_lockstep of runs that do not share their inputs (here two record lengths) is smooth of each."""
    f = _filter(model, flight)
    times, _, track = flight
    z = _draws(flight, 2)
    results = [f.run_lockstep(times[:n], z[:1, :n], MEASUREMENT, q=track.station_params()[:n])[0] for n in (200, 300)]
    _assert_same_smoothing(f, results)


def test_bad_shapes_and_nan_are_refused_before_any_run(model, flight):
    f = _filter(model, flight)
    times, _, track = flight
    z = _draws(flight, 2)
    with pytest.raises(ValueError, match="runs"):
        f.run_lockstep(times, z[0], MEASUREMENT, q=track.station_params())
    with pytest.raises(ValueError, match="z"):
        f.run_lockstep(times[:-1], z, MEASUREMENT, q=track.station_params())
    z[1, 10, 2] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        f.run_lockstep(times, z, MEASUREMENT, q=track.station_params())
    with pytest.raises(ValueError, match="q"):
        f.run_lockstep(times, z[:1], MEASUREMENT)


def test_vm_backend_runs_each_run_alone_with_the_same_results(model, flight):
    vm = load("launcher", backend="casadi-vm")
    times, truth, track = flight
    x0, P0 = initial_estimate(Case(20, "large"), truth[0], TUNING["P0_floor"])
    f = vm.filter("ekf", x0, P0, TUNING["Q"], gate="none", t0=times[0])
    short = slice(0, 60)
    z = _draws(flight, 2)[:, short]
    results = f.run_lockstep(times[short], z, MEASUREMENT, q=track.station_params()[short])
    compiled = _filter(model, flight).run_lockstep(times[short], z, MEASUREMENT, q=track.station_params()[short])
    for a, b in zip(results, compiled):
        np.testing.assert_allclose(a.x, b.x, rtol=1e-12)


def test_bundle_makefile_compiles_the_lockstep_unit_to_nothing(model, tmp_path):
    """Without the library's SYMKF_LANES (the bundle's strict C99 flags) the unit has no code."""
    unit = Path(model.build.directory) / f"launcher_ekf_step_{MEASUREMENT}_lockstep.c"
    obj = tmp_path / "lockstep.o"
    subprocess.run(compiler().split() + ["-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-O1", "-c", "-o",
                                         str(obj), str(unit)], check=True)
    assert b"run_lockstep" not in obj.read_bytes()
    assert "SYMKF_LANES" not in (Path(model.build.directory) / "Makefile").read_text()


def test_lockstep_only_for_double_builds_and_when_asked():
    for family in ("ekf", "ukf"):
        asked = {f"{family}_lockstep": True}
        assert lockstep.enabled(make_config("launcher", **asked), family) == (platform.machine() in
                                                                             ("x86_64", "AMD64"))
        assert not lockstep.enabled(make_config("launcher", precision="float", **asked), family)
        assert not lockstep.enabled(make_config("launcher"), family)           # the default build has none

"""The UKF's sigma points in SIMD lanes (codegen/c_backend/lanes.py): the host library propagates
them 4 at a time with libmvec on an AVX2 CPU; the flight bundle compiles the scalar code only.

A whole 20 Hz flight through the lanes agrees with the scalar sigma points (``ukf_lanes=False``)
to round-off: libmvec's sin/cos differ from libm's by a few ulp, and the filter carries that."""
import subprocess
from pathlib import Path

import numpy as np
import pytest

from symkf.codegen import make_config
from symkf.codegen.c_backend import lanes
from symkf.codegen.compilation import compiler
from symkf.models import launcher as L
from symkf.runtime import load
from symkf.scenarios.launcher.campaign import TUNING, Case, case_flight, initial_estimate

AVX2 = "avx2" in Path("/proc/cpuinfo").read_text() if Path("/proc/cpuinfo").exists() else False


@pytest.fixture(scope="module")
def scalar():
    return load("launcher", backend="compiled", ukf_lanes=False)


@pytest.fixture(scope="module")
def lanes_build():
    """The library with the lanes (an option: the default library computes what the bundle computes)."""
    return load("launcher", backend="compiled", ukf_lanes=True)


def _run(model, family="ukf", seed=11):
    times, truth, track = case_flight(20, L.T_INSERTION, "radar_wgs84")
    x0, P0 = initial_estimate(Case(20, "small"), truth[0], TUNING["P0_floor"])
    f = model.filter(family, x0, P0, TUNING["Q"], gate="none", t0=times[0], **({"kappa": 0.0} if family == "ukf" else {}))
    result = f.run(times, track.noisy(np.random.default_rng(seed)), "radar_wgs84", q=track.station_params())
    return result, truth


@pytest.mark.skipif(not AVX2, reason="this CPU has no AVX2: the library runs the scalar sigma points")
def test_whole_flight_in_lanes_equals_scalar_to_round_off(lanes_build, scalar):
    (fast, truth), (slow, _) = _run(lanes_build), _run(scalar)
    assert np.all(np.asarray(fast.status) == 0) and np.all(np.asarray(slow.status) == 0)
    x_fast, x_slow = np.asarray(fast.x), np.asarray(slow.x)
    assert not np.array_equal(x_fast, x_slow), "the lanes ran: libmvec's round-off is not libm's"
    sigma = np.sqrt(np.einsum("kii->ki", np.asarray(slow.P)))
    # measured: 4.4e-7 of a standard deviation at most in x, 4.1e-8 of sigma_i sigma_j in P, over the flight
    assert np.max(np.abs(x_fast - x_slow) / sigma) < 1e-5
    P_fast, P_slow = np.asarray(fast.P), np.asarray(slow.P)
    assert np.max(np.abs(P_fast - P_slow) / np.einsum("ki,kj->kij", sigma, sigma)) < 1e-5


def test_ekf_has_no_lanes(lanes_build, scalar):
    np.testing.assert_array_equal(np.asarray(_run(lanes_build, "ekf")[0].x), np.asarray(_run(scalar, "ekf")[0].x))


def test_library_calls_libmvec_and_the_scalar_build_does_not(lanes_build, scalar):
    fast, slow = (Path(m.build.library).read_bytes() for m in (lanes_build, scalar))
    for symbol in (b"_ZGVdN4v_sin", b"_ZGVdN4v_cos", b"launcher_lanes_fd_sigma_centre_free_plain"):
        assert symbol in fast and symbol not in slow


def test_bundle_makefile_compiles_the_scalar_code_only(lanes_build, tmp_path):
    """Without the library's SYMKF_LANES (the bundle's Makefile flags), the lanes unit compiles to
    no code and the scalar unit does not call it: the flight bundle is the scalar C99."""
    directory = Path(lanes_build.build.directory)
    for unit in ("launcher_lanes.c", "launcher_fn_fd_sigma_centre_free_plain.c"):
        obj = tmp_path / (unit[:-2] + ".o")
        subprocess.run(compiler().split() + ["-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-O1",
                                             "-fno-math-errno", "-c", "-o", str(obj), str(directory / unit)], check=True)
        text = obj.read_bytes()
        assert b"_ZGVdN4v" not in text and b"launcher_lanes_fd" not in text
    makefile = (directory / "Makefile").read_text()
    assert "SYMKF_LANES" not in makefile and "openmp" not in makefile


def test_lanes_only_when_asked_and_for_double_builds_on_x86_64():
    assert not lanes.enabled(make_config("launcher"))             # the default library: the bundle's scalar code
    assert not lanes.enabled(make_config("launcher", precision="float", ukf_lanes=True))
    assert not lanes.enabled(make_config("launcher", ukf_lanes=False))
    assert lanes.host_flags(make_config("launcher", ukf_lanes=False), "launcher_lanes.c") == []


@pytest.mark.skipif(not AVX2, reason="this CPU has no AVX2: the library runs the scalar sigma points")
def test_update_lanes_only_when_asked(lanes_build, scalar):
    """``ukf_lanes_update``: h at the sigma points in lanes too (libmvec's atan2); off by default."""
    update = load("launcher", backend="compiled", ukf_lanes=True, ukf_lanes_update=True)
    default, asked = (Path(m.build.library).read_bytes() for m in (lanes_build, update))
    for symbol in (b"_ZGVdN4vv_atan2", b"launcher_lanes_h_radar_wgs84_at_sigma"):
        assert symbol in asked and symbol not in default
    (fast, _), (slow, _) = _run(update), _run(scalar)
    sigma = np.sqrt(np.einsum("kii->ki", np.asarray(slow.P)))
    # measured: 3.2e-7 of a standard deviation at most in x over the flight
    assert 0 < np.max(np.abs(np.asarray(fast.x) - np.asarray(slow.x)) / sigma) < 1e-5


def test_point_code_hoists_the_uniform_terms_and_refuses_what_it_cannot_write():
    import casadi as ca
    t, x = ca.SX.sym("t"), ca.SX.sym("x", 2)
    f = ca.Function("f", [t, x], [ca.vertcat(ca.sin(x[0]) * ca.cos(t), x[1] + 2 * t)], {"cse": True})
    uniform, lane, outputs = lanes.point_code(f, varying=1)
    assert any("cos(" in line for line in uniform) and not any("cos(" in line for line in lane)
    assert any("sin(" in line for line in lane) and len(outputs) == 2
    assert lanes._writable(f)
    assert not lanes._writable(ca.Function("g", [t, x], [ca.erfinv(x[0]) * t]))

"""A UKF with kappa = 0 (centre weight exactly 0) does not propagate its centre sigma point
(codegen/model_functions.py ``fd_at_points_weighted``): whole flights equal, bit for bit, the
general kernel's (``ukf_centre_free=False``), which propagates all 2n + 1 points; with kappa != 0
the general kernel is what runs."""
import numpy as np
import pytest

from symkf.models import launcher as L
from symkf.runtime import load
from symkf.scenarios.launcher.campaign import TUNING, Case, case_flight, initial_estimate


@pytest.fixture(scope="module")
def general():
    return load("launcher", backend="compiled", ukf_centre_free=False)


def _flight(seed: int = 5):
    times, truth, track = case_flight(20, L.T_INSERTION)
    z = track.noisy(np.random.default_rng(seed))
    x0, P0 = initial_estimate(Case(20, "large"), truth[0])
    return times, z, track.station_params(), x0, P0


def _run(model, kappa: float, flight):
    times, z, q, x0, P0 = flight
    f = model.filter("ukf", x0, P0, TUNING["Q"], kappa=kappa, gate="none", t0=times[0])
    return f.run(times, z, measurement="radar", q=q)


@pytest.mark.parametrize("kappa", [0.0, 1.0])
def test_whole_flight_equals_the_general_kernel_bit_for_bit(launcher_compiled, general, kappa):
    flight = _flight()
    fast, full = _run(launcher_compiled, kappa, flight), _run(general, kappa, flight)
    assert len(flight[0]) == 8687 and np.all(np.asarray(fast.status) == 0)
    np.testing.assert_array_equal(np.asarray(fast.x), np.asarray(full.x))
    np.testing.assert_array_equal(np.asarray(fast.P), np.asarray(full.P))
    # the run did move: the estimate is not the prior held
    assert np.abs(np.asarray(fast.x)[-1] - flight[3]).max() > 1e3


def test_centre_free_kernel_is_the_one_generated_by_default(launcher_compiled, general):
    """The default build holds the centre-free propagation; the general one does not."""
    def units(model):
        return {p.name for p in model.build.directory.glob("*_fd_sigma_centre_free*.c")}
    assert units(launcher_compiled) and not units(general)

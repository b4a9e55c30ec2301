"""Launcher EKF/UKF: compiled step == NumPy reference, compiled run == compiled steps, Jacobians."""
import numpy as np
import pytest

from symkf.codegen import make_config
from symkf.codegen.model_functions import ModelFunctions
from symkf.models import get_model
from symkf.models import launcher as L
from symkf.runtime.reference import ReferenceFilter
from symkf.scenarios.launcher.truth import propagate, radar_track

P0 = np.diag([10.0, 1e-4, 1e-4, 1000.0, 1e-5, 1e-5]) ** 2
Q = np.diag([1.0, 1e-8, 1e-8, 1.0, 1e-14, 1e-14])


@pytest.fixture(scope="module")
def flight():
    """120 steps at 20 Hz from lift-off: truth, radar draws, station parameters."""
    times = np.arange(121) * 0.05
    truth = propagate(times)
    track = radar_track(times, truth)
    return times, truth, track.noisy(np.random.default_rng(7)), track.station_params()


def _scaled_error(a, b, scale):
    return np.max(np.abs(a - b) / scale)


@pytest.mark.parametrize("family", ["ekf", "ukf"])
def test_compiled_step_equals_numpy_reference(launcher_compiled, flight, family):
    times, truth, z, q = flight
    x0 = truth[0] + np.array([10.0, 1e-8, 1e-8, 1000.0, 1e-8, 1e-8])
    compiled = launcher_compiled.filter(family, x0, P0, Q)
    reference = ReferenceFilter("launcher", family, x0, P0, Q)
    worst_x = worst_P = 0.0
    for k in range(1, len(times)):
        dt = times[k] - times[k - 1]
        compiled.step(times[k - 1], dt, z[k], "radar", q=q[k])
        reference.step(times[k - 1], dt, z[k], "radar", q[k])
        sigma = np.sqrt(np.diag(reference.P))
        worst_x = max(worst_x, _scaled_error(compiled.x, reference.x, sigma))
        worst_P = max(worst_P, _scaled_error(compiled.P, reference.P, np.outer(sigma, sigma)))
    # Errors in units of the filter's own standard deviations. The UKF's P - U^T U cancels ~4 digits
    # (prior sigma_r 1 km -> posterior 10 m) on a P with cond ~1e18 (metres vs 1e-8 rad), so its
    # round-off shows at ~1e-8 sigma; the EKF's Joseph form stays at ~1e-15.
    tolerance = {"ekf": (1e-12, 1e-10), "ukf": (1e-7, 1e-6)}[family]
    assert worst_x < tolerance[0] and worst_P < tolerance[1], (worst_x, worst_P)
    assert np.all(np.abs(compiled.x - truth[-1]) < 5 * np.sqrt(np.diag(compiled.P)) + [1, 1e-3, 1e-3, 1, 1e-6, 1e-6])


def test_derived_jacobians_match_central_differences():
    """F = df_d/dx and H = dh/dx, compared in scaled units (state errors of ~[100 m/s, 0.01 rad,
    0.01 rad, 1 km, 1e-4 rad, 1e-4 rad]) so that every entry counts."""
    model = get_model("launcher")
    fns = ModelFunctions(model, make_config("launcher"))
    p = np.array(model.param_defaults)
    scale = np.array([100.0, 1e-2, 1e-2, 1e3, 1e-4, 1e-4])
    station = L.station_params(1)
    for t in (10.0, 140.0, 400.0):
        x = propagate(np.array([t]))[0]
        F = np.array(fns.jac_fd(t, 0.05, x, [], p)) * scale / scale[:, None]
        H = np.array(fns.jac_h["radar"](t, x, [], p, station)) * scale
        F_fd, H_fd = np.zeros_like(F), np.zeros_like(H)
        for j in range(6):
            e = np.zeros(6)
            e[j] = 1e-4 * scale[j]
            F_fd[:, j] = (np.array(fns.fd(t, 0.05, x + e, [], p)) - np.array(fns.fd(t, 0.05, x - e, [], p))).ravel() \
                / (2e-4 * scale)
            H_fd[:, j] = (np.array(fns.h["radar"](t, x + e, [], p, station))
                          - np.array(fns.h["radar"](t, x - e, [], p, station))).ravel() / 2e-4
        assert np.max(np.abs(F - F_fd)) < 1e-6 * np.max(np.abs(F)), t
        assert np.max(np.abs(H - H_fd) / np.abs(H).max(axis=1, keepdims=True)) < 1e-6, t

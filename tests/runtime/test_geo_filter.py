"""Paper 003 continuous-discrete EKF: compiled == NumPy reference, masks, bad input."""
import numpy as np
import pytest

from symkf.models import geo_satellite as geo
from symkf.models import get_model
from symkf.runtime import SymkfError
from symkf.runtime.reference import NumpyCDEKF
from symkf.scenarios.geo.closed_loop import LoopSettings, _load, simulate

X0 = geo.initial_errors(geo.TABLE6) + np.r_[np.zeros(3), 1e-3 * np.ones(3), np.zeros(11)]
U = np.array([0.3, -0.1, 0.2, 0.05])
NO_TORQUE = np.zeros(4)      # an update before any predict: the wheels' input at that time, said


@pytest.fixture(scope="module")
def compiled():
    return _load()


def make_pair(compiled, P0=None):
    tune = geo.filter_tuning()
    rng = np.random.default_rng(3)
    if P0 is None:
        L = rng.normal(size=(17, 17)) * 0.1
        P0 = tune["P0"] * 0.1 + L @ L.T
    ekf = compiled.filter("cd_ekf", X0, P0, tune["Q"], R=tune["R"], gate="none")   # the reference has no gate
    ref = NumpyCDEKF(get_model("geo_satellite"), X0, P0, tune["Q"], tune["R"])
    return ekf, ref


def test_predict_matches_numpy_reference(compiled):
    ekf, ref = make_pair(compiled)
    for k in range(5):
        ekf.predict(k * 0.125, 0.125, u=U)
        ref.predict(k * 0.125, 0.125, u=U)
    np.testing.assert_allclose(ekf.x, ref.x, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(ekf.P, ref.P, rtol=1e-9, atol=1e-13)
    assert np.array_equal(ekf.P, ekf.P.T)


@pytest.mark.parametrize("name", ["sun_sensor", "earth_sensor", "gyro", "tacho"])
def test_update_matches_numpy_reference(compiled, name):
    ekf, ref = make_pair(compiled)
    z = np.asarray(get_model("geo_satellite").measurements[name].sigma) * 3 + 0.01
    ekf.update(z, measurement=name, u=NO_TORQUE)
    ref.update(z, measurement=name)
    np.testing.assert_allclose(ekf.x, ref.x, rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(ekf.P, ref.P, rtol=1e-8, atol=1e-12)


def test_step_equals_predict_then_update(compiled):
    a, _ = make_pair(compiled)
    b, _ = make_pair(compiled)
    z = np.array([1e-3, -2e-3, 5e-4, 1e-3])
    a.step(0.0, 0.125, z, measurement="gyro", u=U)
    b.predict(0.0, 0.125, u=U)
    b.update(z, measurement="gyro")
    np.testing.assert_allclose(a.x, b.x, rtol=1e-14, atol=1e-18)
    np.testing.assert_allclose(a.P, b.P, rtol=1e-13, atol=1e-16)


def test_masked_gyro_changes_nothing(compiled):
    """Whatever a masked (failed) gyro reads, even NaN, the update is the same."""
    z = np.array([1e-3, -2e-3, 5e-4, 1e-3])
    results = []
    for value in (z[1], 1e3, np.nan):
        ekf, _ = make_pair(compiled)
        ekf.update(np.r_[z[0], value, z[2:]], measurement="gyro", mask=[1, 0, 1, 1], u=NO_TORQUE)
        results.append((ekf.x.copy(), ekf.P.copy()))
    for x, P in results[1:]:
        np.testing.assert_array_equal(x, results[0][0])
        np.testing.assert_array_equal(P, results[0][1])
    full, _ = make_pair(compiled)
    full.update(z, measurement="gyro", u=NO_TORQUE)
    assert not np.allclose(full.x, results[0][0])             # the mask did something


def test_masked_component_equals_dropping_it_in_the_reference(compiled):
    ekf, ref = make_pair(compiled)
    z = np.array([1e-3, -2e-3, 5e-4, 1e-3])
    ekf.update(z, measurement="gyro", mask=[0, 1, 0, 1], u=NO_TORQUE)
    ref.update(z, measurement="gyro", mask=[0, 1, 0, 1])
    np.testing.assert_allclose(ekf.x, ref.x, rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(ekf.P, ref.P, rtol=1e-8, atol=1e-12)


def test_all_gyros_masked_is_predict_only(compiled):
    a, _ = make_pair(compiled)
    b, _ = make_pair(compiled)
    a.step(0.0, 0.125, np.full(4, np.nan), measurement="gyro", mask=np.zeros(4), u=U)
    b.predict(0.0, 0.125, u=U)
    np.testing.assert_array_equal(a.x, b.x)
    np.testing.assert_array_equal(a.P, b.P)


def test_not_positive_definite_innovation_fails_cleanly(compiled):
    tune = geo.filter_tuning()
    R = dict(tune["R"], sun_sensor=-np.eye(1) * 10.0)        # S = H P H^T + R < 0
    with pytest.raises(ValueError, match=r"R\[sun_sensor\]: not positive definite"):
        compiled.filter("cd_ekf", X0, tune["P0"], tune["Q"], R=R)
    ekf = compiled.filter("cd_ekf", X0, tune["P0"], tune["Q"], R=tune["R"])
    ekf.measurements["sun_sensor"]["R"][:] = -10.0                # past the contract: the C code refuses it too
    x, P = ekf.x.copy(), ekf.P.copy()
    with pytest.raises(SymkfError, match="NOT_PD"):
        ekf.update([0.0], measurement="sun_sensor", u=NO_TORQUE)
    np.testing.assert_array_equal(ekf.x, x)
    np.testing.assert_array_equal(ekf.P, P)


def test_closed_loop_compiled_equals_numpy_reference(compiled):
    """Same truth, sensors, noise draws and PID: the two filters agree to round-off."""
    runs = {e: simulate(LoopSettings(duration=20.0, estimator=e, failed_gyros=("B",)), compiled)
            for e in ("ekf", "numpy-ekf")}
    a, b = runs["ekf"], runs["numpy-ekf"]
    assert a.t.size == 161
    np.testing.assert_allclose(a.estimate, b.estimate, rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(a.sigma, b.sigma, rtol=1e-7, atol=1e-12)
    np.testing.assert_allclose(a.truth, b.truth, rtol=1e-9, atol=1e-13)
    assert np.abs(a.estimate[-1] - a.truth[-1])[3:9].max() < 1e-4      # and it tracks the truth


def test_smoother_is_after_the_fact_and_never_feeds_the_controller(compiled):
    """The closed loop with and without the CD-EKF RTS smoothing is bit-identical (the smoother
    runs once the loop has ended); the smoothing beats the filter's whole-run error, and the
    compiled backward pass equals the NumPy reference's over the same loop."""
    with_rts = simulate(LoopSettings(20.0, "ekf"), compiled)
    without = simulate(LoopSettings(20.0, "ekf", smooth=False), compiled)
    for name in ("truth", "estimate", "sigma", "wheel_torque", "body_torque"):
        np.testing.assert_array_equal(getattr(with_rts, name), getattr(without, name))
    assert without.smoothed is None and not with_rts.smooth_status.any()
    with pytest.raises(ValueError, match="no smoothed estimate"):
        without.estimation_error("rate", smoothed=True)
    for block in ("angle", "rate", "momentum", "bias"):
        filtered, smoothed = (np.sqrt(np.mean(with_rts.estimation_error(block, s) ** 2)) for s in (False, True))
        assert smoothed < 0.5 * filtered, block
    reference = simulate(LoopSettings(20.0, "numpy-ekf"), compiled)
    scale = np.sqrt(np.diag(geo.filter_tuning()["P0"]))
    np.testing.assert_allclose(reference.estimate / scale, with_rts.estimate / scale, rtol=0, atol=1e-12)
    np.testing.assert_allclose(reference.smoothed / scale, with_rts.smoothed / scale, rtol=0, atol=1e-12)

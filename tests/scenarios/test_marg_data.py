"""The gradient-descent filter on real recordings (BROAD trials, the x-io example): loaders, three paths, BROAD metric.

Skipped with a reason saying where to get the recordings when they are absent (BROAD:
https://github.com/dlaidig/broad; x-io: https://github.com/xioTechnologies/Fusion).
"""
import numpy as np
import pytest
from scipy.io import loadmat
from scipy.spatial.transform import Rotation

from symkf.runtime import load
from symkf.runtime.reference.gradient_descent import ReferenceGradientDescent
from symkf.scenarios.marg.filter import initial_orientation, make_filter, samples
from symkf.scenarios.marg.data import WHERE_BROAD, WHERE_XIO, data_dir, load_recording, run_recording
from symkf.scenarios.marg.broad_metric import broad_error_angles, broad_errors, error_rotation_vectors, to_enu

BROAD_TRIAL = data_dir() / "broad" / "01_undisturbed_slow_rotation_A.mat"
XIO_CSV = data_dir() / "fusion_sensor_data.csv"

needs_broad = pytest.mark.skipif(not BROAD_TRIAL.exists(),
                                 reason=f"BROAD recording {BROAD_TRIAL} is absent; {WHERE_BROAD}")
needs_xio = pytest.mark.skipif(not XIO_CSV.exists(),
                               reason=f"x-io recording {XIO_CSV} is absent; {WHERE_XIO}")


@pytest.fixture(scope="module")
def compiled():
    return load("marg", backend="compiled")


@pytest.fixture(scope="module")
def broad():
    return load_recording(BROAD_TRIAL)


@needs_broad
def test_broad_loader_converts_scalar_first_reference(broad):
    raw = loadmat(BROAD_TRIAL)
    np.testing.assert_array_equal(broad.reference[:, 3], raw["opt_quat"][:, 0])
    np.testing.assert_array_equal(broad.reference[:, :3], raw["opt_quat"][:, 1:])
    assert broad.gyro.shape == (56940, 3) and broad.movement.sum() == int(raw["movement"].sum())
    np.testing.assert_allclose(broad.dt[1:], 1 / 285.714285714, rtol=1e-9)


@needs_broad
@pytest.mark.parametrize("form,mode", [("simple", "marg"), ("full", "marg"), ("simple", "imu")])
def test_compiled_run_equals_numpy_reference_on_broad(compiled, broad, form, mode):
    rec = broad.head(2000)
    filt = make_filter(compiled, form, beta=0.1)
    run = run_recording(compiled, filt, rec, mode)
    z = samples(rec.acc, rec.mag, mode)
    q0 = initial_orientation(compiled, z[0], mode)
    reference = ReferenceGradientDescent("marg", f"gd_{form}", q0, p=[0.1, filt.p[1]])
    if mode == "marg":
        np.testing.assert_allclose(q0, reference.initial(z[0]), atol=1e-15)
    assert not run.failed_steps.size
    np.testing.assert_allclose(run.x, reference.run(rec.time, z, mode, u=rec.gyro), atol=1e-12, rtol=0)


@needs_xio
def test_compiled_step_run_and_reference_agree_on_xio_with_real_dt(compiled):
    rec = load_recording(XIO_CSV).head(1500)
    assert rec.dt[1:].std() > 0            # non-uniform timestamps are used as they are
    run = run_recording(compiled, make_filter(compiled, "simple", beta=0.1), rec)
    z = samples(rec.acc, rec.mag)
    q0 = initial_orientation(compiled, z[0])
    stepper = make_filter(compiled, "simple", beta=0.1, q0=q0)
    steps = [stepper.run(rec.time[:1], z[:1], "marg", u=rec.gyro[:1]).x[0]]      # dt[0] = 0: step() needs > 0
    for k in range(1, len(rec)):
        stepper.step(rec.time[k - 1], rec.dt[k], z[k], "marg", u=rec.gyro[k])
        steps.append(stepper.x.copy())
    np.testing.assert_allclose(run.x, np.array(steps), atol=1e-15, rtol=0)
    reference = ReferenceGradientDescent("marg", "gd_simple", q0, p=[0.1, stepper.p[1]])
    np.testing.assert_allclose(run.x, reference.run(rec.time, z, "marg", u=rec.gyro), atol=1e-12, rtol=0)


def test_broad_metric_definitions():
    ref = Rotation.random(50, random_state=4).as_quat()
    heading_only = (Rotation.from_euler("z", 10, degrees=True) * Rotation.from_quat(ref)).as_quat()
    angles = np.degrees(broad_error_angles(heading_only, ref))
    # acos near 1 resolves ~1e-8 rad (2e-6 deg): the metric's own precision
    np.testing.assert_allclose(angles, np.tile([10, 10, 0], (50, 1)), atol=1e-5)
    tilt_only = (Rotation.from_euler("x", 7, degrees=True) * Rotation.from_quat(ref)).as_quat()
    np.testing.assert_allclose(np.degrees(broad_error_angles(tilt_only, ref)), np.tile([7, 0, 7], (50, 1)), atol=1e-5)
    np.testing.assert_allclose(np.degrees(error_rotation_vectors(-tilt_only, ref)), np.tile([7, 0, 0], (50, 1)),
                               atol=1e-9)
    # sign of the quaternion does not matter
    np.testing.assert_allclose(broad_error_angles(-ref, ref), 0, atol=1e-7)
    # the NWU -> ENU alignment: a sensor facing magnetic north in NWU faces +y (north) in ENU
    east_axis = Rotation.from_quat(to_enu(np.array([[0, 0, 0, 1.0]]))[0]).apply([1, 0, 0])
    np.testing.assert_allclose(east_axis, [0, 1, 0], atol=1e-15)


@needs_broad
def test_broad_rmse_of_reference_is_zero_and_filter_is_accurate(compiled, broad):
    enu_to_nwu = Rotation.from_euler("z", -90, degrees=True)
    finite = np.isfinite(broad.reference).all(axis=1)
    as_nwu = np.tile([0, 0, 0, 1.0], (len(broad), 1))
    as_nwu[finite] = (enu_to_nwu * Rotation.from_quat(broad.reference[finite])).as_quat()
    zero = broad_errors(as_nwu, broad)
    assert zero["total"] < 1e-5 and zero["samples"] > 30000
    run = run_recording(compiled, make_filter(compiled, "simple", beta=0.041), broad)
    errors = broad_errors(run.x, broad)
    # measured 2.1 deg total / 0.73 deg inclination (trial 01, beta = 0.041); bound with margin
    assert errors["total"] < 3.0 and errors["inclination"] < 1.5, errors

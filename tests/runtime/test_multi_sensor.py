"""Multi-sensor runs (codegen/c_backend/multi_loop.py, runtime/multi_runs.py): a two-sensor
attitude user model (sun sensor at 1 Hz, magnetometer at 10 Hz, gyro as input) in one compiled
run equals the step-by-step loop, with NIS per measurement; the bundle builds strictly."""
import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from symkf.codegen import build_model
from symkf.runtime import load, smooth
from symkf.runtime.reference import ManifoldReference
from symkf.runtime.reference.rts import mekf_rts

MODEL = str(Path(__file__).with_name("sun_mag_model.py"))
SUN, MAG = np.array([0.8, 0.6, 0.0]), np.array([0.2, 0.0, 0.9797958971132712])
N, DT = 200, 0.1
X0 = np.r_[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]
ERROR_STATES = {"mekf": 6, "ekf": 7}          # the MEKF carries a 3-vector attitude error


@pytest.fixture(scope="module")
def record():
    rng = np.random.default_rng(0)
    times = np.arange(N) * DT
    rates = np.stack([0.1 * np.sin(0.3 * times), 0.05 * np.ones(N), -0.08 * np.cos(0.2 * times)], axis=1)
    body = [attitude.inv() for attitude in _truth(times)]
    z = {"sun": np.array([r.apply(SUN) for r in body]) + rng.normal(0, 0.01, (N, 3)),
         "mag": np.array([r.apply(MAG) for r in body]) + rng.normal(0, 0.03, (N, 3))}
    mask = {"sun": np.zeros((N, 3)), "mag": np.ones((N, 3))}
    mask["sun"][::10] = 1.0                        # 1 Hz beside the 10 Hz magnetometer
    mask["mag"][57, 2] = 0.0                       # one component missing
    gyro = rates + np.array([0.01, -0.02, 0.005]) + rng.normal(0, 0.001, (N, 3))
    return times, z, mask, gyro


@pytest.fixture(scope="module", params=["compiled", "casadi-vm"])
def sun_mag(request):
    return load(MODEL, backend=request.param)


def _filter(compiled, family):
    n = ERROR_STATES[family]
    return compiled.filter(family, X0, np.eye(n) * 0.01, np.eye(n) * 1e-5)


def _step_loop(f, record):
    """The flight loop written out: predict, then each present measurement in the model's order."""
    times, z, mask, gyro = record
    states, nis = [], {"sun": np.full(N, np.nan), "mag": np.full(N, np.nan)}
    for k in range(N):
        if k:
            f.predict(times[k - 1], DT, u=gyro[k])
        for m in ("sun", "mag"):
            if mask[m][k].any():
                f.update(z[m][k], m, mask=mask[m][k], u=gyro[k])
                nis[m][k] = f.y(m) @ np.linalg.solve(f.S(m), f.y(m))
        states.append(f.x.copy())
    return np.array(states), nis


@pytest.mark.parametrize("family", ["mekf", "ekf"])
def test_multi_sensor_run_equals_the_step_loop(sun_mag, record, family):
    times, z, mask, gyro = record
    f = _filter(sun_mag, family)
    result = f.run_multi(times, z, mask=mask, u=gyro)
    loop = _filter(sun_mag, family)
    loop.t = times[0]
    states, nis = _step_loop(loop, record)
    np.testing.assert_allclose(result.x, states, rtol=0, atol=1e-12)
    np.testing.assert_allclose(f.x, loop.x, rtol=0, atol=1e-12)
    np.testing.assert_allclose(f.P, loop.P, rtol=0, atol=1e-14)
    assert f.t == loop.t == times[-1]
    assert not result.status.any() and not any(s.any() for s in result.update_status.values())
    for m in ("sun", "mag"):
        np.testing.assert_array_equal(np.isnan(result.nis[m]), np.isnan(nis[m]))
        np.testing.assert_allclose(result.nis[m], nis[m], rtol=1e-9, atol=1e-12)
        np.testing.assert_array_equal(result.present[m], mask[m].any(axis=1))
    assert result.nis_dof["sun"][10] == 3 and result.nis_dof["sun"][11] == 0 and result.nis_dof["mag"][57] == 2
    # consistent: the averaged NIS near the dof of each sensor
    assert 2.0 < np.nanmean(result.nis["mag"]) < 4.0 and 1.5 < np.nanmean(result.nis["sun"]) < 4.5


def test_a_measurement_not_given_is_absent(sun_mag, record):
    times, z, mask, gyro = record
    only_mag = _filter(sun_mag, "mekf").run_multi(times, {"mag": z["mag"]}, mask={"mag": mask["mag"]}, u=gyro)
    by_run = _filter(sun_mag, "mekf").run(times, z["mag"], "mag", mask=mask["mag"], u=gyro)
    np.testing.assert_allclose(only_mag.x, by_run.x, rtol=0, atol=1e-12)
    assert np.isnan(only_mag.nis["sun"]).all() and not only_mag.present["sun"].any()


def test_a_multi_sensor_run_smooths(sun_mag, record):
    times, z, mask, gyro = record
    f = _filter(sun_mag, "ekf")
    result = smooth(f, f.run_multi(times, z, mask=mask, u=gyro))
    filtered, smoothed = np.trace(result.P, axis1=1, axis2=2), np.trace(result.P_smooth, axis1=1, axis2=2)
    assert np.all(smoothed <= filtered * (1 + 1e-9)) and smoothed[100] < 0.7 * filtered[100]


def test_the_mekf_smoother_on_the_manifold(sun_mag, record):
    """The error-state RTS smoother (codegen/families/rts.py on the MEKF's chart): unit
    quaternions, attitude and gyro-bias errors against the truth below the filter's."""
    times, z, mask, gyro = record
    f = sun_mag.filter("mekf", X0, np.eye(6) * 0.01, np.diag([1e-6] * 3 + [1e-8] * 3))
    result = smooth(f, f.run_multi(times, z, mask=mask, u=gyro))
    np.testing.assert_allclose(np.linalg.norm(result.x_smooth[:, :4], axis=1), 1.0, atol=1e-12)
    truth, bias = _truth(times), np.array([0.01, -0.02, 0.005])

    def degrees(x):
        return np.degrees([(t.inv() * Rotation.from_quat(q)).magnitude() for t, q in zip(truth, x[:, :4])])
    assert degrees(result.x_smooth).mean() < 0.85 * degrees(result.x).mean()
    assert np.abs(result.x_smooth[:, 4:] - bias).mean() < 0.5 * np.abs(result.x[:, 4:] - bias).mean()
    assert np.all(np.trace(result.P_smooth, axis1=1, axis2=2) <= np.trace(result.P, axis1=1, axis2=2) * (1 + 1e-9))


def test_the_mekf_smoother_equals_its_numpy_reference(sun_mag, record):
    times, z, mask, gyro = record
    Q = np.diag([1e-6] * 3 + [1e-8] * 3)
    f = sun_mag.filter("mekf", X0, np.eye(6) * 0.01, Q)
    result = smooth(f, f.run_multi(times, z, mask=mask, u=gyro))
    reference = ManifoldReference(MODEL, "mekf", X0, np.eye(6) * 0.01, Q)
    xs, Ps = mekf_rts(reference, result.x, result.P, *_run_times(times), u=gyro)
    np.testing.assert_allclose(result.x_smooth, xs, rtol=0, atol=1e-11)
    np.testing.assert_allclose(result.P_smooth, Ps, rtol=0, atol=1e-13)


def _run_times(times):
    """A run's per-step t (start of step k) and dt (the first 0)."""
    return np.concatenate([times[:1], times[:-1]]), np.diff(times, prepend=times[:1])


def _truth(times):
    rates = np.stack([0.1 * np.sin(0.3 * times), 0.05 * np.ones(N), -0.08 * np.cos(0.2 * times)], axis=1)
    attitude, out = Rotation.identity(), []
    for k in range(N):
        if k:
            attitude = attitude * Rotation.from_rotvec(rates[k - 1] * DT)
        out.append(attitude)
    return out


def test_run_multi_refuses_what_it_cannot_run(sun_mag, record):
    times, z, mask, gyro = record
    f = _filter(sun_mag, "mekf")
    with pytest.raises(ValueError, match="not among"):
        f.run_multi(times, {"star": z["sun"]}, u=gyro)
    with pytest.raises(ValueError, match="have no z"):
        f.run_multi(times, {"mag": z["mag"]}, mask={"sun": mask["sun"]}, u=gyro)
    bad = z["mag"].copy()
    bad[5, 0] = np.nan
    x_before = f.x.copy()
    with pytest.raises(ValueError, match="NaN"):
        f.run_multi(times, {"sun": z["sun"], "mag": bad}, mask=mask, u=gyro)
    np.testing.assert_array_equal(f.x, x_before)


def test_the_bundle_with_multi_sensor_loops_builds_strictly(tmp_path):
    result = build_model(MODEL)
    manifest = json.loads(result.manifest.read_text())
    for name in manifest["sources"] + ["sun_mag.h", "Makefile"]:
        shutil.copy(result.directory / name, tmp_path / name)
    proc = subprocess.run(["make", "-j2", "-C", str(tmp_path), "all"], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "warning" not in proc.stderr.lower()
    header = (tmp_path / "sun_mag.h").read_text()
    assert "SYMKF_API int sun_mag_mekf_run_multi(int n_steps" in header
    exported = subprocess.run(["nm", "-D", "--defined-only", str(tmp_path / "libsun_mag.so")],
                              capture_output=True, text=True).stdout
    assert "sun_mag_mekf_run_multi" in exported and "sun_mag_ekf_smooth_run" in exported

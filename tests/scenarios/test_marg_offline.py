"""The offline pass of the MARG MEKF (scenarios/marg/mekf_offline.py, model marg_mekf_scale of
models/marg_mekf.py) on synthetic recordings: its two-sided heading vote and half-sample gyro,
the three paths (NumPy reference, compiled step, compiled run; the smoother against its NumPy
reference), and a gyro scale-factor error the smoother recovers."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from symkf.models import marg_mekf
from symkf.runtime import load
from symkf.runtime.reference.manifold import ManifoldReference
from symkf.runtime.reference.rts import mekf_rts
from symkf.scenarios.marg import mekf, mekf_offline
from symkf.scenarios.marg.data import Recording

RATE_HZ = 285.714
FIELD_ENU = np.array([0.0, 25.0, -43.0])          # north and down: BROAD's ENU frame is magnetic north
SCALE_ERROR = np.array([0.0, 0.0, -0.004])        # the gyro z axis reads 0.4 % low
BIAS = np.array([0.002, -0.001, 0.008])


@pytest.fixture(scope="module")
def compiled():
    return mekf_offline.load_model()


def _recording(seconds: float, seed: int = 3) -> tuple[Recording, np.ndarray]:
    """1.6 s at rest (the rest rule needs 1.5 s), then turning one way about the sensor's tilted z
    axis (0.8 rad/s, as trial 28 turns one way), 1.6 s at rest at the end; the gyro with
    ``SCALE_ERROR`` and ``BIAS``, noise on every sensor. Returns the recording and the true
    sensor -> ENU quaternions."""
    rng = np.random.default_rng(seed)
    n = int(seconds * RATE_HZ)
    time = np.arange(n) / RATE_HZ
    moving = (time > 1.6) & (time < seconds - 1.6)
    rate = np.where(moving[:, None], [0.05, -0.03, 0.8], 0.0)
    attitude, truth = Rotation.from_euler("xyz", [0.2, -0.1, 0.4]), []
    for k in range(n):
        if k:
            attitude = attitude * Rotation.from_rotvec(rate[k] / RATE_HZ)
        truth.append(attitude.as_quat())
    truth = np.array(truth)
    to_body = Rotation.from_quat(truth).inv()
    gyro = (1 + SCALE_ERROR) * rate + BIAS + rng.normal(0, 2e-3, (n, 3))
    acc = to_body.apply([0.0, 0.0, 9.81]) + rng.normal(0, 0.05, (n, 3))
    mag = to_body.apply(FIELD_ENU) + rng.normal(0, 0.3, (n, 3))
    return Recording("synthetic", time, gyro, acc, mag), truth


def test_heading_vote_drops_isolated_passes_and_keeps_runs():
    accepted = np.zeros(40)
    accepted[[3, 20, 21]] = 1            # isolated passes inside a disturbed stretch
    accepted[30:40] = 1                  # an undisturbed run (to the end)
    voted = mekf_offline.voted_heading(accepted, 5)
    np.testing.assert_array_equal(np.flatnonzero(voted), np.arange(30, 40))
    assert not mekf_offline.voted_heading(np.r_[np.zeros(5), 1.0, np.zeros(5)], 5).any()
    np.testing.assert_array_equal(mekf_offline.voted_heading(np.ones(7), 5), np.ones(7, dtype=bool))


def test_gyro_half_a_sample_later():
    recording, _ = _recording(4.0)
    u = mekf_offline.gyro_rates(recording)
    np.testing.assert_array_equal(u[:-1], 0.5 * (recording.gyro[:-1] + recording.gyro[1:]))
    np.testing.assert_array_equal(u[-1], recording.gyro[-1])


def test_offline_masks_differ_from_the_online_ones_only_in_the_heading():
    recording, _ = _recording(4.0)
    recording.mag[500:503] *= 1.2        # a short disturbance: online masks it, the vote too
    online, offline = mekf.masks(recording), mekf_offline.masks(recording)
    columns = [c for c in range(7) if c != mekf_offline.HEADING]
    np.testing.assert_array_equal(online[:, columns], offline[:, columns])
    assert np.all(offline[:, 3] <= online[:, 3]) and not offline[500:503, 3].any()


def test_scale_model_reference_step_run_and_smoother_agree(compiled):
    """marg_mekf_scale (series transition, sequential update): NumPy reference == compiled step ==
    compiled run over 800 samples (rest, then turning), and the compiled smoother == the NumPy
    error-state RTS over the same run."""
    recording, _ = _recording(2.8)
    n = len(recording)
    z, mask, u = mekf.measurements(recording), mekf_offline.masks(recording), mekf_offline.gyro_rates(recording)
    assert 0 < mask[:, 4].sum() < n
    run = mekf_offline.smooth_recording(compiled, recording)
    stepped = mekf_offline.make_filter(compiled, recording)
    ref = ManifoldReference(marg_mekf.build(gyro_scale=True), "mekf", stepped.x, stepped.P, stepped.Q)
    assert ref.transition == "series"
    stepped.update(z[0], "marg", q=recording.mag[0], mask=mask[0], u=u[0])
    ref.u = u[0]
    ref.update(z[0], "marg", 0.0, q=recording.mag[0], mask=mask[0])
    time = recording.time
    for k in range(1, n):
        dt = time[k] - time[k - 1]
        stepped.step(time[k - 1], dt, z[k], "marg", q=recording.mag[k], mask=mask[k], u=u[k])
        ref.step(time[k - 1], dt, z[k], "marg", q=recording.mag[k], mask=mask[k], u=u[k])
        np.testing.assert_allclose(run.x[k], stepped.x, rtol=0, atol=1e-14)
        np.testing.assert_allclose(run.P[k], stepped.P, rtol=0, atol=1e-18)
    np.testing.assert_allclose(stepped.x, ref.x, rtol=1e-10, atol=1e-13)
    np.testing.assert_allclose(stepped.P, ref.P, rtol=1e-9, atol=1e-18)
    reference = ManifoldReference(marg_mekf.build(gyro_scale=True), "mekf", run.x[0], run.P[0], stepped.Q)
    t_steps, dt_steps = np.concatenate([time[:1], time[:-1]]), np.diff(time, prepend=time[:1])
    xs, Ps = mekf_rts(reference, run.x, run.P, t_steps, dt_steps, u=u)
    np.testing.assert_allclose(run.x_smooth, xs, rtol=0, atol=1e-11)
    np.testing.assert_allclose(run.P_smooth, Ps, rtol=0, atol=1e-13)


def test_smoother_recovers_a_gyro_scale_factor_error(compiled):
    """Turning one way for 57 s with the gyro's z axis 0.4 % low: the smoothed k_z within two of
    its sigmas of it, that sigma below half the prior, one constant for the whole run, and the
    smoothed attitude closer to the truth than the online filter's (which has no k)."""
    recording, truth = _recording(60.0)
    smoothed = mekf_offline.smooth_recording(compiled, recording)
    online = mekf.run_recording(load("marg_mekf"), recording)
    k, sigma = smoothed.x_smooth[0, 7:], np.sqrt(np.diag(smoothed.P_smooth[0])[6:])
    assert abs(k[2] - SCALE_ERROR[2]) < 2 * sigma[2] and sigma[2] < 0.5 * marg_mekf.SCALE_PRIOR_SIGMA, (k, sigma)
    assert np.all(np.abs(k[:2]) < 1e-4), k                          # x, y hardly turn: k stays near 0
    assert np.all(np.abs(smoothed.x_smooth[:, 7:] - k) < 1e-6)       # one constant for the whole run

    def error_deg(q):
        return np.degrees((Rotation.from_quat(truth).inv() * Rotation.from_quat(q)).magnitude())
    moving = (recording.time > 1.6) & (recording.time < recording.time[-1] - 1.6)
    smooth_error, online_error = error_deg(smoothed.x_smooth[:, :4])[moving], error_deg(online.q)[moving]
    assert np.sqrt(np.mean(smooth_error**2)) < 0.5 * np.sqrt(np.mean(online_error**2)), \
        (np.sqrt(np.mean(smooth_error**2)), np.sqrt(np.mean(online_error**2)))

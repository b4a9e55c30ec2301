"""The fixed-interval smoothers (codegen/families/rts.py, runtime/smoothing.py): the EKF's RTS
smoother against an RTS written in NumPy over recorded predictions, the unscented RTS smoother
against FilterPy's ``UnscentedKalmanFilter.rts_smoother`` (Julier points) and a NumPy Särkkä form,
compiled and CasADi-VM backward loops, masked, gated and refused steps, and the errors."""
from pathlib import Path

import numpy as np
import pytest

from symkf.codegen.spec import STATUS_GATED, STATUS_NOT_PD
from symkf.runtime import SymkfError, load, smooth
from symkf.runtime.reference import ReferenceFilter
from symkf.runtime.reference.rts import ekf_forward, rts, ukf_rts

MODEL = str(Path(__file__).with_name("rts_radar_model.py"))
DT, N = 0.1, 120
X0, P0 = np.array([0.0, 90.0, 1100.0]), np.eye(3) * 100.0
Q = np.eye(3) * 0.1          # PSD: Q dt = 0.01 I per step, FilterPy's Q
ROUND_OFF = dict(rtol=1e-9, atol=1e-9)


def record(seed: int = 200, accelerate: bool = True):
    """Ranges of the aircraft (FilterPy's radar case) and the known accelerations u."""
    rng = np.random.default_rng(seed)
    u = rng.normal(0.0, 1.0, (N, 1)) if accelerate else np.zeros((N, 1))
    x, z = X0.copy(), []
    for k in range(N):
        x = x + DT * np.array([x[1], u[k, 0], 0.0])
        z.append(np.hypot(x[0], x[2]) + rng.normal(0.0, 10 ** 0.5))
    return np.array(z)[:, None], u


@pytest.fixture(scope="module", params=["compiled", "casadi-vm"])
def radar(request):
    return load(MODEL, backend=request.param)


def times():
    return np.arange(N) * DT, np.full(N, DT)


def test_ekf_smoother_equals_numpy_rts_with_masks_and_inputs(radar):
    z, u = record()
    mask = np.ones((N, 1))
    mask[30:45] = 0.0                         # a gap: those steps are predictions
    run = radar.ekf(X0, P0, Q).run_steps(np.full(N, DT), z, "range", mask=mask, u=u, smooth=True)
    t, dt = times()
    ref = ekf_forward(ReferenceFilter(MODEL, "ekf", X0, P0, Q), t, dt, z, "range", np.zeros((N, 0)), mask, u=u)
    np.testing.assert_allclose(run.x, ref["x"], **ROUND_OFF)
    xs, Ps = rts(ref["x"], ref["P"], ref["x_pred"], ref["P_pred"], ref["F"])
    np.testing.assert_allclose(run.x_smooth, xs, **ROUND_OFF)
    np.testing.assert_allclose(run.P_smooth, Ps, **ROUND_OFF)
    assert not run.smooth_status.any()
    np.testing.assert_array_equal(run.x_smooth[-1], run.x[-1])
    # smoothing uses the whole record: never less certain than the filter, much more in the gap
    filtered, smoothed = np.trace(run.P, axis1=1, axis2=2), np.trace(run.P_smooth, axis1=1, axis2=2)
    assert np.all(smoothed <= filtered * (1 + 1e-12))
    assert smoothed[37] < 0.5 * filtered[37]


def test_gated_updates_are_predictions_of_the_backward_pass(radar):
    z, u = record(seed=7)
    z[[20, 50, 51, 90]] += 400.0              # outliers the gate refuses
    f = radar.ekf(X0, P0, Q)
    f.set_gate("range", probability=0.999)
    run = f.run_steps(np.full(N, DT), z, "range", u=u, smooth=True)
    gated = run.status == STATUS_GATED
    assert gated[[20, 50, 51, 90]].all()
    t, dt = times()
    ref = ekf_forward(ReferenceFilter(MODEL, "ekf", X0, P0, Q), t, dt, z, "range", np.zeros((N, 0)),
                      np.ones((N, 1)), u=u, updated=~gated)
    np.testing.assert_allclose(run.x, ref["x"], **ROUND_OFF)
    xs, Ps = rts(ref["x"], ref["P"], ref["x_pred"], ref["P_pred"], ref["F"])
    np.testing.assert_allclose(run.x_smooth, xs, **ROUND_OFF)
    np.testing.assert_allclose(run.P_smooth, Ps, **ROUND_OFF)


def test_unscented_smoother_equals_numpy_sarkka_form(radar):
    z, u = record(seed=3)
    run = radar.ukf(X0, P0, Q, kappa=1.0).run_steps(np.full(N, DT), z, "range", u=u, smooth=True)
    t, dt = times()
    xs, Ps = ukf_rts(ReferenceFilter(MODEL, "ukf", X0, P0, Q, kappa=1.0), run.x, run.P, t, dt, u=u)
    np.testing.assert_allclose(run.x_smooth, xs, **ROUND_OFF)
    np.testing.assert_allclose(run.P_smooth, Ps, **ROUND_OFF)


def test_unscented_smoother_equals_filterpy_rts_smoother():
    """FilterPy's UKF RTS test case (Julier sigma points, kappa = 0) as a symkf user model."""
    kalman = pytest.importorskip("filterpy.kalman", reason='FilterPy is the oracle: pip install -e ".[test]"')
    z, _ = record(seed=200, accelerate=False)
    compiled = load(MODEL, backend="compiled")
    run = compiled.ukf(X0, P0, Q, kappa=0.0, R={"range": np.array([[10.0]])}).run_steps(
        np.full(N, DT), z, "range", u=np.zeros(1), smooth=True)

    def fx(x, dt):
        return (np.eye(3) + dt * np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])) @ x

    def hx(x):
        return np.array([np.sqrt(x[0] ** 2 + x[2] ** 2)])

    def filterpy_ukf():
        ukf = kalman.UnscentedKalmanFilter(3, 1, DT, hx=hx, fx=fx, points=kalman.JulierSigmaPoints(3, kappa=0.0))
        ukf.Q, ukf.R, ukf.x, ukf.P = np.eye(3) * 0.01, 10.0, X0.copy(), P0.copy()
        return ukf
    mu, cov = filterpy_ukf().batch_filter(list(z))[:2]
    np.testing.assert_allclose(run.x, mu, **ROUND_OFF)          # the same forward filter here
    xs, Ps, _ = filterpy_ukf().rts_smoother(run.x, run.P)
    np.testing.assert_allclose(run.x_smooth, xs, **ROUND_OFF)
    np.testing.assert_allclose(run.P_smooth, Ps, **ROUND_OFF)


def test_smooth_afterwards_equals_run_with_smooth_and_ignores_later_settings(radar):
    z, u = record(seed=5)
    f = radar.ekf(X0, P0, Q)
    plain = f.run_steps(np.full(N, DT), z, "range", u=u)
    f.Q = Q * 50.0                            # the run recorded the Q it ran with
    later = smooth(f, plain)
    again = radar.ekf(X0, P0, Q).run_steps(np.full(N, DT), z, "range", u=u, smooth=True)
    np.testing.assert_array_equal(later.x_smooth, again.x_smooth)
    np.testing.assert_array_equal(later.P_smooth, again.P_smooth)


def test_a_refused_step_is_carried_over_by_the_backward_pass(radar):
    """A step the forward run refused kept its state (row j = row j - 1): no transition between
    the two rows, so smoothed row j - 1 is smoothed row j."""
    z, u = record(seed=9)
    f = radar.ekf(X0, P0, Q)
    run = f.run_steps(np.full(N, DT), z, "range", u=u)
    j = 60
    run.status[j] = STATUS_NOT_PD
    run.x[j], run.P[j] = run.x[j - 1], run.P[j - 1]
    smoothed = smooth(f, run)
    np.testing.assert_array_equal(smoothed.x_smooth[j - 1], smoothed.x_smooth[j])
    np.testing.assert_array_equal(smoothed.P_smooth[j - 1], smoothed.P_smooth[j])
    assert not np.array_equal(smoothed.x_smooth[j - 2], smoothed.x_smooth[j - 1])


def test_a_failed_backward_step_raises_or_is_kept(radar):
    z, u = record(seed=11)
    f = radar.ekf(X0, P0, Q)
    run = f.run_steps(np.full(N, DT), z, "range", u=u)
    run.P[40] = -np.eye(3)                    # not a covariance: P^- of step 41 has no Cholesky factor
    # step 40 restarts from its filtered row, -I: step 39's smoothed P is then not PSD, refused too
    with pytest.raises(SymkfError, match=r"SYMKF_ERR_NOT_PD.*backward step\(s\) \[40, 39\]"):
        smooth(f, run)
    kept = smooth(f, run, errors="keep")
    assert kept.smooth_status[40] == kept.smooth_status[39] == STATUS_NOT_PD
    assert np.count_nonzero(kept.smooth_status) == 2
    np.testing.assert_array_equal(kept.x_smooth[40], run.x[40])
    np.testing.assert_array_equal(kept.P_smooth[39], run.P[39])


def test_smooth_refuses_what_it_cannot_smooth(radar):
    z, u = record()
    f = radar.ekf(X0, P0, Q)
    run = f.run_steps(np.full(N, DT), z, "range", u=u)
    with pytest.raises(ValueError, match="records no run inputs"):
        smooth(f, type(run)(run.x, run.P, run.status))
    with pytest.raises(ValueError, match="do not fit"):
        smooth(f, type(run)(run.x[:, :2], run.P[:, :2, :2], run.status, run.inputs))
    with pytest.raises(ValueError, match="errors"):
        smooth(f, run, errors="ignore")

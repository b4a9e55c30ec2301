"""The continuous-discrete EKF's RTS smoother (codegen/families/cd_ekf.py ``cd_ekf_smooth``):
on a linear model it must be the discrete RTS smoother with the exact Phi = expm(A dt) and
Q_d (Van Loan), it equals its NumPy reference (runtime/reference/rts.py ``cd_ekf_rts``) on the
compiled and CasADi-VM backends, and on the 17-state geo satellite of paper 003 (multi-rate
sensors, failed gyros masked); refused and failed steps follow the rules of the other smoothers."""
from pathlib import Path

import numpy as np
import pytest
from scipy.linalg import cho_factor, cho_solve, expm

from symkf.codegen.spec import STATUS_GATED, STATUS_NOT_PD
from symkf.models import geo_satellite as geo
from symkf.models import get_model
from symkf.runtime import SymkfError, load, smooth
from symkf.runtime.reference import NumpyCDEKF
from symkf.runtime.reference.rts import cd_ekf_rts

MODEL = str(Path(__file__).with_name("cd_linear_model.py"))
N, DT = 200, 0.1
Q = np.diag([1e-4, 1e-2, 1e-3])
X0, P0 = np.array([1.0, 0.0, 0.5]), np.diag([1.0, 1.0, 0.5])
ROUND_OFF = dict(rtol=1e-9, atol=1e-11)


def linear_model():
    import importlib.util
    spec = importlib.util.spec_from_file_location("cd_linear_model", MODEL)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def record(seed: int = 1):
    rng = np.random.default_rng(seed)
    z = np.sin(0.8 * np.arange(N) * DT)[:, None] + rng.normal(0.0, 0.3, (N, 1))
    mask = np.ones((N, 1))
    mask[60:90] = 0.0                        # a gap: those steps are predictions
    return z, mask


@pytest.fixture(scope="module", params=["compiled", "casadi-vm"])
def linear(request):
    return load(MODEL, backend=request.param)


def exact_discrete_rts(lm, z, mask, R):
    """Kalman filter and RTS smoother of dx/dt = A x with Phi = expm(A dt) and Q_d by Van Loan's
    method (Q_d = Phi * [upper right block of expm([[-A, Q], [0, A^T]] dt)])."""
    A = np.array([[0.0, 1.0, 0.0], [-lm.OMEGA ** 2, -2 * lm.DAMPING, lm.OMEGA ** 2], [0.0, 0.0, -lm.DRIFT]])
    Phi = expm(A * DT)
    Qd = Phi @ expm(np.block([[-A, Q], [np.zeros((3, 3)), A.T]]) * DT)[:3, 3:]
    H = np.array([[1.0, 0.0, 1.0]])
    x, P, rows = X0.copy(), P0.copy(), []
    for k in range(N):
        x, P = Phi @ x, Phi @ P @ Phi.T + Qd
        x_pred, P_pred = x, P
        if mask[k, 0]:
            K = P @ H.T @ np.linalg.inv(H @ P @ H.T + R)
            x, P = x + K @ (z[k] - H @ x), P - K @ H @ P
        rows.append((x_pred, P_pred, x, 0.5 * (P + P.T)))
    x_pred, P_pred, x, P = (np.array(a) for a in zip(*rows))
    xs, Ps = x.copy(), P.copy()
    for k in range(N - 2, -1, -1):
        G = cho_solve(cho_factor(P_pred[k + 1]), Phi @ P[k]).T
        xs[k] = x[k] + G @ (xs[k + 1] - x_pred[k + 1])
        Ps[k] = P[k] + G @ (Ps[k + 1] - P_pred[k + 1]) @ G.T
    return x, P, xs, Ps


def test_linear_cd_smoother_is_the_exact_discrete_rts(linear):
    """RK4 with h = dt / 80 (the model's sub-steps) leaves a truncation of ~1e-13 here (it shrinks
    256-fold per 4-fold sub-steps: 2e-11 at 20 sub-steps), so the two agree to round-off."""
    lm = linear_model()
    z, mask = record()
    R = np.array([[lm.POSITION_SIGMA ** 2]])
    run = linear.filter("cd_ekf", X0, P0, Q, R={"position": R}).run_steps(np.full(N, DT), z, "position",
                                                                         mask=mask, smooth=True)
    x, P, xs, Ps = exact_discrete_rts(lm, z, mask, R)
    np.testing.assert_allclose(run.x, x, rtol=0, atol=1e-12)
    np.testing.assert_allclose(run.P, P, rtol=0, atol=1e-12)
    np.testing.assert_allclose(run.x_smooth, xs, rtol=0, atol=1e-12)
    np.testing.assert_allclose(run.P_smooth, Ps, rtol=0, atol=1e-12)
    assert not run.smooth_status.any()
    filtered, smoothed = np.trace(run.P, axis1=1, axis2=2), np.trace(run.P_smooth, axis1=1, axis2=2)
    assert np.all(smoothed <= filtered * (1 + 1e-12))
    assert smoothed[80] < 0.5 * filtered[80]                  # inside the gap the future helps most


def test_gated_updates_are_predictions_of_the_cd_backward_pass(linear):
    """Outliers the chi-square gate refuses: those steps are predictions of both passes, as in
    the exact discrete filter and smoother that skip their updates."""
    lm = linear_model()
    z, mask = record(seed=4)
    z[[20, 120, 121, 170]] += 5.0                    # 17 sigma of the measurement
    R = np.array([[lm.POSITION_SIGMA ** 2]])
    f = linear.filter("cd_ekf", X0, P0, Q, R={"position": R})
    f.set_gate("position", probability=0.999)
    run = f.run_steps(np.full(N, DT), z, "position", mask=mask, smooth=True)
    gated = run.status == STATUS_GATED
    assert gated[[20, 120, 121, 170]].all() and gated.sum() == 4
    x, P, xs, Ps = exact_discrete_rts(lm, z, mask * ~gated[:, None], R)
    np.testing.assert_allclose(run.x, x, rtol=0, atol=1e-12)
    np.testing.assert_allclose(run.x_smooth, xs, rtol=0, atol=1e-12)
    np.testing.assert_allclose(run.P_smooth, Ps, rtol=0, atol=1e-12)


def test_linear_cd_smoother_equals_numpy_reference(linear):
    z, mask = record(seed=2)
    lm = linear_model()
    R = {"position": np.array([[lm.POSITION_SIGMA ** 2]])}
    run = linear.filter("cd_ekf", X0, P0, Q, R=R).run_steps(np.full(N, DT), z, "position", mask=mask, smooth=True)
    ref = NumpyCDEKF(lm.build(), X0, P0, Q, R, substeps=80)
    xs, Ps = cd_ekf_rts(ref, run.x, run.P, run.inputs["t"], run.inputs["dt"])
    np.testing.assert_allclose(run.x_smooth, xs, **ROUND_OFF)
    np.testing.assert_allclose(run.P_smooth, Ps, **ROUND_OFF)


def test_refused_step_is_carried_and_failed_backward_step_is_reported(linear):
    z, mask = record(seed=3)
    f = linear.filter("cd_ekf", X0, P0, Q)
    run = f.run_steps(np.full(N, DT), z, "position", mask=mask)
    j = 120
    run.status[j] = STATUS_NOT_PD            # as a refused step leaves it: row j = row j - 1
    run.x[j], run.P[j] = run.x[j - 1], run.P[j - 1]
    carried = smooth(f, run)
    np.testing.assert_array_equal(carried.x_smooth[j - 1], carried.x_smooth[j])
    np.testing.assert_array_equal(carried.P_smooth[j - 1], carried.P_smooth[j])
    run.P[40] = -np.eye(3)                    # not a covariance: the backward step refuses it
    with pytest.raises(SymkfError, match=r"SYMKF_ERR_NOT_PD.*backward step\(s\) \[40, 39\]"):
        smooth(f, run)                        # 39 reads row 40's restart (-I): its smoothed P is not PSD
    kept = smooth(f, run, errors="keep")
    assert kept.smooth_status[40] == kept.smooth_status[39] == STATUS_NOT_PD
    assert np.count_nonzero(kept.smooth_status) == 2
    np.testing.assert_array_equal(kept.x_smooth[40], run.x[40])
    np.testing.assert_array_equal(kept.P_smooth[39], run.P[39])


# ---------------------------------------------------------------------- paper 003's satellite
def geo_record(n_ticks: int = 160):
    """Multi-rate sensor records of the geo closed loop's rates (gyro A failed: NaN, masked)."""
    rng = np.random.default_rng(5)
    model = get_model("geo_satellite")
    times = np.arange(n_ticks) / 8.0
    z, mask = {}, {}
    for name, every in (("sun_sensor", 1), ("gyro", 1), ("earth_sensor", 2), ("tacho", 4)):
        sigma = np.asarray(model.measurements[name].sigma)
        z[name] = rng.normal(0.0, 1.0, (n_ticks, sigma.size)) * sigma
        mask[name] = np.zeros((n_ticks, sigma.size))
        mask[name][::every] = 1.0
    mask["gyro"][:, 0] = 0.0
    z["gyro"][:, 0] = np.nan
    u = rng.normal(0.0, 0.05, (n_ticks, 4))
    return times, z, mask, u


def test_geo_compiled_smoother_equals_numpy_reference():
    compiled = load("geo_satellite")
    tune = geo.filter_tuning()
    x0 = geo.initial_errors(geo.TABLE6) * 0.5
    times, z, mask, u = geo_record()
    f = compiled.filter("cd_ekf", x0, tune["P0"], tune["Q"], R=tune["R"], gate="none")
    run = smooth(f, f.run_multi(times, z, mask=mask, u=u))
    assert not run.smooth_status.any()
    substeps = int(get_model("geo_satellite").codegen_defaults.get("rk4_substeps", 1))
    ref = NumpyCDEKF(get_model("geo_satellite"), x0, tune["P0"], tune["Q"], tune["R"], substeps)
    xs, Ps = cd_ekf_rts(ref, run.x, run.P, run.inputs["t"], run.inputs["dt"], run.inputs["u"])
    # round-off relative to each state's smoothed sigma (the covariances span 1 .. 1e-16)
    sigma = np.sqrt(np.einsum("kii->ki", Ps))
    np.testing.assert_allclose((run.x_smooth - xs) / sigma, 0.0, atol=1e-12)
    np.testing.assert_allclose((run.P_smooth - Ps) / (sigma[:, :, None] * sigma[:, None, :]), 0.0, atol=1e-10)
    filtered, smoothed = np.trace(run.P, axis1=1, axis2=2), np.trace(run.P_smooth, axis1=1, axis2=2)
    assert np.all(smoothed <= filtered * (1 + 1e-9))

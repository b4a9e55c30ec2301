"""Paper 003 model: eqs (1)-(5), Table 2 geometry, units, gyro-failure geometry ranks."""
import itertools

import numpy as np
import pytest

from symkf.codegen.discretize import continuous_dynamics, discrete_dynamics
from symkf.models import geo_satellite as geo
from symkf.models import get_model
from symkf.scenarios.geo.closed_loop import closed_loop_eigenvalues, geometry_rank, least_squares_rates

STATE = np.r_[0.01, -0.02, 0.03, 0.1, -0.2, 0.3, 1e-3, -2e-3, 3e-3, -10, 5, 10, -15, 1e-4, 2e-4, -1e-4, 3e-5]
TORQUE = np.array([0.3, -0.1, 0.2, 0.05])


def xdot(model, x=STATE, u=TORQUE):
    return np.asarray(continuous_dynamics(model)(0, x, u, [], [])).ravel()


def test_model_has_17_states_11_measurements_and_the_cd_ekf():
    m = get_model("geo_satellite")
    assert m.nx == 17 and [v.name for v in m.states] == list(geo.STATE_NAMES)
    assert sum(meas.size for meas in m.measurements.values()) == 11
    assert m.filters == ("cd_ekf",)


def test_gyro_geometry_eq1_unit_axes_and_table2_angles():
    G = geo.gyro_geometry()
    np.testing.assert_allclose(np.linalg.norm(G, axis=1), 1.0, atol=1e-15)
    assert G[0, 1] == pytest.approx(-np.sin(np.radians(54.7)))
    assert G[1, 0] == pytest.approx(np.sin(np.radians(60)) * np.sin(np.radians(54.7)))


def test_wheel_pyramid_eq2_and_minimum_norm_distribution():
    W = geo.wheel_pyramid()
    assert np.linalg.matrix_rank(W) == 3
    wheel, body = geo.control_law()([1e-3, 2e-3, 3e-3], [0.01, -0.02, 0.03], [1e-4, 0, -1e-4])
    np.testing.assert_allclose(W @ np.asarray(wheel).ravel(), np.asarray(body).ravel(), rtol=1e-12)


def test_pid_eq5_table3_gains():
    _, body = geo.control_law()([1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0])
    np.testing.assert_allclose(np.asarray(body).ravel(), [0.5 * 2.78125, 0.5 * 364.5, 2.0 * 1152.0])


def test_kinematics_eq4_is_inverted_exactly():
    rates = xdot(get_model("geo_satellite"))[3:6]
    psi, phi = STATE[3], STATE[4]
    M = np.array([[1, 0, -np.sin(phi)], [0, np.cos(psi), np.sin(psi) * np.cos(phi)],
                  [0, -np.sin(psi), np.cos(psi) * np.cos(phi)]])
    np.testing.assert_allclose(M @ rates, STATE[6:9], rtol=1e-13)


def test_rigid_body_eq3_balance_with_table2_inertia():
    """-I omegadot = hdot + omega x (I omega + h), with body h = W h_wheels, hdot = W u."""
    d = xdot(get_model("geo_satellite"))
    I = np.array([[81653, 53, -106], [53, 88831, 504], [-106, 504, 17758]], float)
    W = geo.wheel_pyramid()
    w = STATE[6:9]
    residual = I @ d[6:9] + W @ TORQUE + np.cross(w, I @ w + W @ STATE[9:13])
    assert np.abs(residual).max() < 1e-12
    np.testing.assert_array_equal(d[9:13], TORQUE)
    np.testing.assert_array_equal(d[13:17], 0.0)
    np.testing.assert_array_equal(d[0:3], STATE[3:6])


def test_unit_change_leaves_the_motion_unchanged():
    """Paper units vs SI: the same closed loop (perfect state feedback, 2 Hz ZOH) for 200 s."""
    trajectories = {}
    for units in ("paper", "si"):
        model = geo.build(units)
        step, law = discrete_dynamics(model, 4), geo.control_law(units)
        x = geo.initial_errors(geo.TABLE6, units)
        angles = []
        for k in range(400):
            u = law(x[0:3], x[3:6], x[6:9])[0]
            x = np.asarray(step(k * 0.5, 0.5, x, u, [], [])).ravel()
            angles.append(x[3:9].copy())
        trajectories[units] = (np.array(angles), x)
    np.testing.assert_allclose(trajectories["si"][0], trajectories["paper"][0], rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(trajectories["si"][1][9:13], trajectories["paper"][1][9:13] * geo.IN_LBF, rtol=1e-9)
    assert np.abs(trajectories["paper"][0][0]).max() > 1e-4        # it did move


@pytest.mark.parametrize("failed", [()] + [(g,) for g in "ABCD"])
def test_no_or_one_failed_gyro_keeps_rank_3_and_exact_rates(failed):
    assert geometry_rank(failed) == 3
    omega = np.array([1e-3, -2e-3, 5e-4])
    np.testing.assert_allclose(least_squares_rates(geo.gyro_geometry() @ omega, failed), omega, rtol=1e-12)
    assert closed_loop_eigenvalues(failed).real.max() < 0


@pytest.mark.parametrize("failed", list(itertools.combinations("ABCD", 2)))
def test_every_failed_pair_leaves_omega_unobservable_and_the_loop_unstable(failed):
    assert geometry_rank(failed) == 2
    keep = [i for i in range(4) if "ABCD"[i] not in failed]
    null = np.linalg.svd(geo.gyro_geometry()[keep])[2][-1]        # the rate the gyros cannot see
    assert np.abs(least_squares_rates(geo.gyro_geometry() @ null, failed)).max() < 1e-12
    assert closed_loop_eigenvalues(failed).real.max() > 0


def test_failed_pair_B_C_loses_exactly_the_x_axis():
    keep = [0, 3]
    null = np.linalg.svd(geo.gyro_geometry()[keep])[2][-1]
    np.testing.assert_allclose(np.abs(null), [1, 0, 0], atol=1e-12)
    assert geometry_rank(("A", "B", "C", "D")) == 0


def test_unknown_gyro_and_units_are_named():
    with pytest.raises(ValueError, match="'E'"):
        geometry_rank(("E",))
    with pytest.raises(ValueError, match="units"):
        geo.build("cgs")

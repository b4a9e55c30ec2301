"""Paper 001 equations and the gradient-descent kernels, without recordings.

The derived gradient Jᵀf is checked against Jacobians written here by hand from f (18) and (22)
(the printed (15), (19), (23) have typesetting errors, so they are not used) and against central
finite differences of ½‖f‖²; the filter paths (compiled step, compiled run, NumPy reference)
are compared on synthetic samples, including zero-norm and masked ones.
"""
import casadi as ca
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from symkf.codegen.families.gradient_descent import check_model, model_functions
from symkf.models import get_model
from symkf.models import marg as paper
from symkf.models import quaternion as quat
from symkf.runtime import load
from symkf.runtime.reference.gradient_descent import ReferenceGradientDescent
from symkf.scenarios.marg.filter import initial_orientation, make_filter, samples

RNG = np.random.default_rng(1)


@pytest.fixture(scope="module")
def compiled():
    return load("marg", backend="compiled")


@pytest.fixture(scope="module")
def fns():
    return model_functions(get_model("marg"))


def call(function, *args) -> np.ndarray:
    return np.asarray(function(*args)).ravel()


U0, P0 = np.zeros(3), np.array([0.1, 2.0])      # the gradients do not depend on u or p


def random_unit(n: int = 4) -> np.ndarray:
    v = RNG.normal(size=n)
    return v / np.linalg.norm(v)


def evaluate(expr_fn, *values) -> np.ndarray:
    """Evaluate a symbolic model function on numbers."""
    syms = [ca.SX.sym(f"a{i}", np.size(v)) for i, v in enumerate(values)]
    return np.asarray(ca.Function("f", syms, [expr_fn(*syms)])(*values)).ravel()


# ---------------------------------------------------------------------- conventions
def hamilton_scalar_first(a, b):
    """Hamilton product written independently in the paper's scalar-first order (eq (3), typo-free)."""
    a1, a2, a3, a4 = a
    b1, b2, b3, b4 = b
    return np.array([a1 * b1 - a2 * b2 - a3 * b3 - a4 * b4, a1 * b2 + a2 * b1 + a3 * b4 - a4 * b3,
                     a1 * b3 - a2 * b4 + a3 * b1 + a4 * b2, a1 * b4 + a2 * b3 - a3 * b2 + a4 * b1])


def test_scalar_first_last_round_trip_and_product():
    q, p = random_unit(), random_unit()
    first = evaluate(quat.to_scalar_first, q)
    np.testing.assert_array_equal(first, [q[3], q[0], q[1], q[2]])
    np.testing.assert_array_equal(evaluate(quat.from_scalar_first, first), q)
    np.testing.assert_array_equal(evaluate(lambda v: quat.to_scalar_first(quat.from_scalar_first(v)), first), first)
    # the project's scalar-last Hamilton product is the paper's scalar-first product (3), reordered
    ours = evaluate(quat.hamilton, p, q)
    theirs = hamilton_scalar_first(evaluate(quat.to_scalar_first, p), first)
    np.testing.assert_allclose(evaluate(quat.to_scalar_first, ours), theirs, atol=1e-15)


def test_quaternion_rate_integrates_body_rate_like_scipy():
    q0, omega, dt, n = random_unit(), np.array([0.3, -0.2, 0.5]), 1e-4, 2000
    q = q0.copy()
    for _ in range(n):       # eq (9) with tiny steps, normalised
        q = evaluate(paper.gyro_integration, q, omega, dt)
        q /= np.linalg.norm(q)
    expected = (Rotation.from_quat(q0) * Rotation.from_rotvec(omega * dt * n)).as_quat()
    assert min(np.abs(q - expected).max(), np.abs(q + expected).max()) < 1e-4


def test_euler_angles_eq5_match_scipy_zyx():
    q = random_unit()
    yaw, pitch, roll = Rotation.from_quat(q).as_euler("ZYX")
    np.testing.assert_allclose(evaluate(paper.sensor_euler_angles, q), [yaw, pitch, roll], atol=1e-12)
    # (5) on q itself gives the angles of the inverse rotation
    inv = Rotation.from_quat(q).inv().as_euler("ZYX")
    np.testing.assert_allclose(evaluate(paper.euler_angles, q), inv, atol=1e-12)


def test_objective_component_forms_equal_quaternion_form_11():
    q, d, s = random_unit(), RNG.normal(size=3), RNG.normal(size=3)
    general = evaluate(paper.objective_general, q, d, s)
    np.testing.assert_allclose(evaluate(paper.objective_components, q, d, s), general, atol=1e-14)
    # rotating d into the sensor frame: f + s = R(q)^T d
    np.testing.assert_allclose(general + s, Rotation.from_quat(q).inv().apply(d), atol=1e-14)
    np.testing.assert_allclose(evaluate(paper.objective_gravity, q, s),
                               evaluate(paper.objective_general, q, np.array([0, 0, 1.0]), s), atol=1e-15)
    b = np.array([0.6, 0.0, -0.8])
    np.testing.assert_allclose(evaluate(paper.objective_earth_field, q, b, s),
                               evaluate(paper.objective_general, q, b, s), atol=1e-15)


# ---------------------------------------------------------------------- gradients
def jacobian_gravity_closed_form(q1, q2, q3, q4):
    """∂f_g/∂[q1..q4] differentiated by hand from (18)."""
    return np.array([[-2 * q3, 2 * q4, -2 * q1, 2 * q2],
                     [2 * q2, 2 * q1, 2 * q4, 2 * q3],
                     [0.0, -4 * q2, -4 * q3, 0.0]])


def jacobian_earth_field_closed_form(q1, q2, q3, q4, bx, bz):
    """∂f_b/∂[q1..q4] differentiated by hand from (22), b fixed."""
    return np.array([
        [-2 * bz * q3, 2 * bz * q4, -4 * bx * q3 - 2 * bz * q1, -4 * bx * q4 + 2 * bz * q2],
        [-2 * bx * q4 + 2 * bz * q2, 2 * bx * q3 + 2 * bz * q1, 2 * bx * q2 + 2 * bz * q4, -2 * bx * q1 + 2 * bz * q3],
        [2 * bx * q3, 2 * bx * q4 - 4 * bz * q2, 2 * bx * q1 - 4 * bz * q3, 2 * bx * q2]])


def to_first(v):
    return np.array([v[3], v[0], v[1], v[2]])


@pytest.mark.parametrize("trial", range(5))
def test_derived_gradients_match_closed_forms(fns, trial):
    q = RNG.normal(size=4)       # not unit on purpose: the identity Jᵀf holds for any q
    a, m = random_unit(3), random_unit(3)
    b = np.array([RNG.uniform(0.2, 1), 0.0, RNG.uniform(-1, 1)])
    q1, q2, q3, q4 = to_first(q)
    f_g = evaluate(paper.objective_gravity, q, a)
    f_b = evaluate(paper.objective_earth_field, q, b, m)
    grad_g = jacobian_gravity_closed_form(q1, q2, q3, q4).T @ f_g
    grad_b = jacobian_earth_field_closed_form(q1, q2, q3, q4, b[0], b[2]).T @ f_b
    b_params = b[[0, 2]]          # measurement 'marg''s parameters [bx, bz]
    for name, args in (("gradient_imu", (np.zeros(0), a)), ("gradient_marg_gravity", (b_params, a))):
        np.testing.assert_allclose(to_first(call(fns[name], q, U0, P0, *args)), grad_g, rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(to_first(call(fns["gradient_marg_earth_field"], q, U0, P0, b_params, m)), grad_b,
                               rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(to_first(call(fns["gradient_marg"], q, U0, P0, b_params, np.r_[a, m])),
                               grad_g + grad_b, rtol=1e-13, atol=1e-13)


def test_derived_gradient_matches_finite_differences(fns):
    """Jᵀf = ∇(½‖f‖²): central differences of the stacked objective (24)."""
    q, a, m = random_unit(), random_unit(3), random_unit(3)
    b = np.array([0.5, 0.0, -0.85])
    half_sq = lambda qq: 0.5 * np.sum(evaluate(paper.objective_stacked, qq, a, b, m) ** 2)  # noqa: E731
    h = 1e-6
    fd = np.array([(half_sq(q + h * e) - half_sq(q - h * e)) / (2 * h) for e in np.eye(4)])
    np.testing.assert_allclose(call(fns["gradient_marg"], q, U0, P0, b[[0, 2]], np.r_[a, m]), fd, atol=1e-8)


def test_model_measurements_are_the_objectives_directions():
    """f = h(q) - z: the model's measurements are (18) and (24) without the samples."""
    model, q, a, m = get_model("marg"), random_unit(), random_unit(3), random_unit(3)
    b = np.array([0.5, 0.0, -0.85])
    h = {name: ca.Function("h", [model.x, meas.q], [meas.h]) for name, meas in model.measurements.items()}
    np.testing.assert_allclose(call(h["imu"], q, np.zeros(0)) - a, evaluate(paper.objective_gravity, q, a), atol=1e-15)
    np.testing.assert_allclose(call(h["marg"], q, b[[0, 2]]) - np.r_[a, m],
                               evaluate(paper.objective_stacked, q, a, b, m), atol=1e-15)


def test_family_refuses_a_model_without_what_it_needs():
    model = get_model("marg")
    del model.functions["earth_field_reference"]
    with pytest.raises(ValueError, match=r"Model.functions\['earth_field_reference'\]"):
        check_model(model)


def test_earth_field_reference_recovers_true_field(fns):
    q = random_unit()
    inclination = np.radians(66.0)
    b_true = np.array([np.cos(inclination), 0.0, -np.sin(inclination)])
    m = Rotation.from_quat(q).inv().apply(b_true)          # what the magnetometer sees
    np.testing.assert_allclose(evaluate(paper.earth_field_reference, q, m), b_true, atol=1e-14)
    np.testing.assert_allclose(call(fns["earth_field_reference"], q, m), b_true[[0, 2]], atol=1e-14)
    # with a wrong heading the reference is still horizontal-north + vertical, same inclination
    q_wrong = (Rotation.from_euler("z", 40, degrees=True) * Rotation.from_quat(q)).as_quat()
    np.testing.assert_allclose(evaluate(paper.earth_field_reference, q_wrong, m), b_true, atol=1e-14)


def test_initial_orientation_triad(fns, compiled):
    for _ in range(20):
        q = random_unit()
        R = Rotation.from_quat(q)
        a = 9.81 * R.inv().apply([0, 0, 1.0])
        m = 45 * R.inv().apply([np.cos(1.1), 0, -np.sin(1.1)])
        q0 = call(fns["initial_orientation"], a, m)
        assert min(np.abs(q0 - q).max(), np.abs(q0 + q).max()) < 1e-12
        np.testing.assert_allclose(initial_orientation(compiled, np.r_[a, m]), q0, atol=1e-15)


# ---------------------------------------------------------------------- compiled filter
def synthetic(n=400, rate=100.0, seed=0):
    """A rotating sensor with consistent gravity and field samples plus noise; jittered dt."""
    rng = np.random.default_rng(seed)
    dt = np.full(n, 1 / rate) * rng.uniform(0.8, 1.2, n)
    dt[0] = 0.0
    omega = np.column_stack([np.sin(np.arange(n) / 30), 0.5 * np.cos(np.arange(n) / 20), 0.3 * np.ones(n)])
    truth = [Rotation.from_euler("ZYX", [30, 10, -20], degrees=True)]
    for k in range(1, n):
        truth.append(truth[-1] * Rotation.from_rotvec(omega[k] * dt[k]))
    field = np.array([np.cos(1.1), 0, -np.sin(1.1)])
    acc = np.array([r.inv().apply([0, 0, 9.81]) for r in truth]) + 0.05 * rng.normal(size=(n, 3))
    mag = np.array([r.inv().apply(40 * field) for r in truth]) + 0.3 * rng.normal(size=(n, 3))
    gyro = omega + 0.01 * rng.normal(size=(n, 3)) + np.array([0.02, -0.01, 0.015])
    return np.cumsum(dt), gyro, acc, mag, np.array([r.as_quat() for r in truth])


def angle_error_deg(q, truth):
    return np.degrees(2 * np.arccos(np.clip(np.abs(np.sum(q * truth, axis=-1)), 0, 1)))


@pytest.mark.parametrize("form", ["simple", "full"])
@pytest.mark.parametrize("mode", ["imu", "marg"])
def test_three_paths_agree_on_synthetic_data(compiled, form, mode):
    times, gyro, acc, mag, _ = synthetic()
    acc[50] = 0.0                  # free fall sample
    mag[60:70] = 0.0               # missing magnetometer (zero-norm)
    acc[80], mag[80] = 0.0, 0.0
    z = samples(acc, mag, mode)
    mask = np.ones_like(z)
    mask[100:110, 3:] = 0.0        # missing magnetometer (masked; NaN there is never read)
    mask[120, :3] = 0.0
    z[mask < 0.5] = np.nan
    q0 = Rotation.from_euler("z", 5, degrees=True).as_quat()
    run = make_filter(compiled, form, beta=0.2, q0=q0).run(times, z, mode, u=gyro, mask=mask)
    stepper = make_filter(compiled, form, beta=0.2, q0=q0)
    first = stepper.run(times[:1], z[:1], mode, u=gyro[:1], mask=mask[:1]).x    # dt[0] = 0: step() needs > 0
    for k in range(1, times.size):
        stepper.step(times[k - 1], times[k] - times[k - 1], z[k], mode, u=gyro[k], mask=mask[k])
        first = np.vstack([first, stepper.x])
    reference = ReferenceGradientDescent("marg", f"gd_{form}", q0, p=[0.2, paper.ALPHA_DEFAULT]).run(
        times, z, mode, u=gyro, mask=mask)
    assert not run.failed_steps.size
    np.testing.assert_allclose(run.x, first, atol=1e-15, rtol=0)
    np.testing.assert_allclose(run.x, reference, atol=1e-13, rtol=0)
    np.testing.assert_allclose(np.linalg.norm(run.x, axis=1), 1.0, atol=1e-14)


@pytest.mark.parametrize("form", ["simple", "full"])
def test_converges_from_a_wrong_start(compiled, form):
    times, gyro, acc, mag, truth = synthetic(n=3000, seed=2)
    q0 = (Rotation.from_euler("ZYX", [60, -30, 40], degrees=True) * Rotation.from_quat(truth[0])).as_quat()
    filt = make_filter(compiled, form, beta=0.5, alpha=50.0, q0=q0)
    run = filt.run(times, samples(acc, mag), "marg", u=gyro)
    error = angle_error_deg(run.x, truth)
    assert error[0] > 50
    assert error[-500:].max() < 3.0, error[-500:].max()


def one_step(compiled, form, q0, z, measurement, gyro, mask=None, dt=0.01):
    f = make_filter(compiled, form, beta=0.3, q0=q0)
    f.step(0.0, dt, z, measurement, u=gyro, mask=mask)
    return f.x.copy()


def test_zero_norm_and_masked_samples_skip_that_correction(compiled, fns):
    q0 = Rotation.from_euler("ZYX", [20, 10, 5], degrees=True).as_quat()
    gyro, dt = np.array([0.1, -0.3, 0.2]), 0.01
    acc, mag, zero = np.array([0.1, 0.2, 9.7]), np.array([20.0, 3.0, -40.0]), np.zeros(3)
    gyro_only = paper_gyro_only(fns, q0, gyro, dt)
    no_acc, no_mag = np.r_[0, 0, 0, 1, 1, 1.0], np.r_[1, 1, 1, 0, 0, 0.0]
    for form in ("simple", "full"):
        np.testing.assert_allclose(one_step(compiled, form, q0, np.r_[zero, zero], "marg", gyro), gyro_only, atol=1e-15)
        np.testing.assert_allclose(one_step(compiled, form, q0, np.r_[acc, mag], "marg", gyro, np.zeros(6)),
                                   gyro_only, atol=1e-15)
        imu = one_step(compiled, form, q0, acc, "imu", gyro)
        np.testing.assert_allclose(one_step(compiled, form, q0, np.r_[acc, zero], "marg", gyro), imu, atol=1e-15)
        np.testing.assert_allclose(one_step(compiled, form, q0, np.r_[acc, mag], "marg", gyro, no_mag), imu, atol=1e-15)
        mag_only = one_step(compiled, form, q0, np.r_[zero, mag], "marg", gyro)
        reference = ReferenceGradientDescent("marg", f"gd_{form}", q0, p=[0.3, paper.ALPHA_DEFAULT])
        np.testing.assert_allclose(mag_only, reference.step(0.0, dt, np.r_[zero, mag], "marg", u=gyro), atol=1e-15)
        np.testing.assert_allclose(one_step(compiled, form, q0, np.r_[acc, mag], "marg", gyro, no_acc), mag_only,
                                   atol=1e-15)
        assert np.all(np.isfinite(mag_only)) and abs(np.linalg.norm(mag_only) - 1) < 1e-15
        assert not np.allclose(mag_only, gyro_only)
    # the full form with a still gyro: mu_t = 0, so gamma_t = 1 and q_nabla = q (no NaN from 0/0)
    np.testing.assert_allclose(one_step(compiled, "full", q0, np.r_[acc, mag], "marg", zero), q0, atol=1e-15)


def paper_gyro_only(fns, q0, gyro, dt):
    q = q0 + dt * call(fns["quaternion_rate"], q0, gyro, P0)
    return q / np.linalg.norm(q)


def test_initial_orientation_six_axis_matches_gravity(compiled):
    for _ in range(10):
        truth = Rotation.from_quat(random_unit())
        acc = 9.81 * truth.inv().apply([0, 0, 1.0])
        q0 = Rotation.from_quat(initial_orientation(compiled, acc, "imu"))
        np.testing.assert_allclose(q0.inv().apply([0, 0, 1.0]), acc / 9.81, atol=1e-12)   # same inclination

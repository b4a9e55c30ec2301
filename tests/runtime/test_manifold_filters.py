"""Generated manifold filters (MEKF, manifold UKF) of a model with a quaternion and two ordinary
states: compiled == NumPy reference to round-off, run == steps, |q| = 1 kept, bad input refused."""
from pathlib import Path

import numpy as np
import pytest

from symkf.models import ModelError, Model
from symkf.runtime import SymkfError, load
from symkf.runtime.reference.manifold import ManifoldReference, exp_rotvec, hamilton, log_quaternion

SPINNER = Path(__file__).resolve().parents[1] / "codegen" / "spinner_model.py"
Q0 = np.array([0.1, -0.2, 0.3, 0.9]) / np.linalg.norm([0.1, -0.2, 0.3, 0.9])
X0 = np.r_[Q0, 0.4, 0.02]
_SIGMA0 = np.sqrt([0.02, 0.03, 0.05, 0.01, 1e-4])
P0 = np.outer(_SIGMA0, _SIGMA0) * (0.8 * np.eye(5) + 0.2)          # correlated, positive definite
QPSD = np.diag([1e-4, 1e-4, 2e-4, 1e-3, 1e-6])
U = np.array([0.3, -0.2])


@pytest.fixture(scope="module")
def spinner():
    return load(SPINNER, backend="compiled")


def _vectors(q, rng=None):
    """Gravity and north directions in the body frame for attitude q (+ noise)."""
    from scipy.spatial.transform import Rotation
    R_t = Rotation.from_quat(q).as_matrix().T
    z = np.r_[R_t @ [0, 0, 1.0], R_t @ [1.0, 0, 0]]
    return z if rng is None else z + rng.normal(0, 0.01, 6)


def _assert_close(a, b, rtol=1e-11, what=""):
    a, b = np.asarray(a), np.asarray(b)
    scale = max(np.max(np.abs(b)), 1e-300)
    assert np.max(np.abs(a - b)) <= rtol * scale, f"{what}: max difference {np.max(np.abs(a - b)):.3e}"


@pytest.fixture(scope="module")
def spinner_left():
    """The same model with the reference-frame (left) error δq ⊗ q̂."""
    return load(SPINNER, backend="compiled", manifold_side="left")


@pytest.mark.parametrize("side", ["right", "left"])
@pytest.mark.parametrize("family", ["mekf", "mukf"])
def test_one_step_equals_numpy_reference(request, family, side):
    spinner = request.getfixturevalue("spinner" if side == "right" else "spinner_left")
    compiled = spinner.filter(family, X0, P0, QPSD, kappa=0.5) if family == "mukf" else \
        spinner.filter(family, X0, P0, QPSD)
    ref = ManifoldReference(SPINNER, family, X0, P0, QPSD, kappa=0.5, side=side)
    truth = hamilton(Q0, exp_rotvec(np.array([0.05, -0.08, 0.1])))
    compiled.predict(0.0, 0.02, u=U)
    ref.predict(0.0, 0.02, u=U)
    _assert_close(compiled.x, ref.x, what="predict x")
    _assert_close(compiled.P, ref.P, what="predict P")
    mask = np.array([1, 1, 1, 0, 1, 1.0])
    z = _vectors(truth)
    compiled.update(z, "vectors", mask=mask)
    ref.update(z, "vectors", 0.02, mask=mask)
    _assert_close(compiled.x, ref.x, what="update x")
    _assert_close(compiled.P, ref.P, what="update P")
    _assert_close(compiled.y("vectors"), ref.y, what="innovation")
    compiled.step(0.02, 0.02, [0.47], "gyro_z", u=U)
    ref.step(0.02, 0.02, [0.47], "gyro_z", u=U)
    _assert_close(compiled.x, ref.x, what="step x")
    _assert_close(compiled.P, ref.P, what="step P")
    # the correction really moved the quaternion (the test is not vacuous)
    assert np.linalg.norm(log_quaternion(hamilton(Q0 * [-1, -1, -1, 1], compiled.x[:4]))) > 0.05


def test_sequential_update_equals_the_batch_reference():
    """manifold_update="sequential" (one scalar update per component, models/marg_mekf.py's choice)
    gives the batch NumPy reference's update to round-off, masked components included; a used
    correlation in R is refused (SYMKF_ERR_ARGS), state unchanged."""
    spinner = load(SPINNER, backend="compiled", manifold_update="sequential")
    compiled = spinner.filter("mekf", X0, P0, QPSD)
    ref = ManifoldReference(SPINNER, "mekf", X0, P0, QPSD)
    z = _vectors(hamilton(Q0, exp_rotvec(np.array([0.05, -0.08, 0.1]))))
    for mask in (np.array([1, 1, 1, 0, 1, 1.0]), np.ones(6)):
        t = compiled.t
        compiled.step(t, 0.02, z, "vectors", mask=mask, u=U)
        ref.step(t, 0.02, z, "vectors", mask=mask, u=U)
        _assert_close(compiled.x, ref.x, what="sequential x")
        _assert_close(compiled.P, ref.P, what="sequential P")
        _assert_close(compiled.S("vectors"), ref.S, what="S")
    assert np.linalg.norm(log_quaternion(hamilton(Q0 * [-1, -1, -1, 1], compiled.x[:4]))) > 0.05
    x, P = compiled.x.copy(), compiled.P.copy()
    R = np.diag(np.square([0.02] * 3 + [0.05] * 3))
    R[0, 1] = R[1, 0] = 1e-4
    compiled.set_R("vectors", R)
    with pytest.raises(SymkfError, match="ARGS.*needs a diagonal R"):
        compiled.update(z, "vectors")
    np.testing.assert_array_equal(compiled.x, x)
    np.testing.assert_array_equal(compiled.P, P)


@pytest.mark.parametrize("side", ["right", "left"])
def test_series_transition_equals_numpy_reference_and_is_close_to_the_step_one(side):
    """manifold_transition="series" (F = I + A dt + (A dt)²/2, A derived by CasADi through the chart):
    compiled == the NumPy reference's chain-rule A to round-off (on the right side the attitude
    drops out of A and is replaced by the identity; on the left it stays: both checked), and the
    covariance differs from F through the RK4 step only by the series' truncation."""
    series = load(SPINNER, backend="compiled", manifold_transition="series", manifold_side=side)
    step = load(SPINNER, backend="compiled", manifold_side=side)
    compiled, through_step = series.filter("mekf", X0, P0, QPSD), step.filter("mekf", X0, P0, QPSD)
    ref = ManifoldReference(SPINNER, "mekf", X0, P0, QPSD, side=side, transition="series")
    z = _vectors(hamilton(Q0, exp_rotvec(np.array([0.05, -0.08, 0.1]))))
    for k in range(3):
        for f in (compiled, through_step):
            f.step(0.02 * k, 0.02, z, "vectors", u=U)
        ref.step(0.02 * k, 0.02, z, "vectors", u=U)
        _assert_close(compiled.x, ref.x, what="series x")
        _assert_close(compiled.P, ref.P, what="series P")
    gap = np.max(np.abs(compiled.P - through_step.P)) / np.max(np.abs(through_step.P))
    assert 1e-12 < gap < 1e-4, gap                 # |A dt| ~ 0.01 here: a truncation of ~|A dt|³


def test_series_transition_needs_the_rk4_step():
    from symkf.codegen.spec import ConfigError
    with pytest.raises(ConfigError, match="manifold_transition 'series' needs manifold_step 'rk4'"):
        load("attitude", backend="compiled", manifold_transition="series")


def test_marg_mekf_numpy_reference_step_and_run_agree():
    """models/marg_mekf.py (series transition, sequential update) on a synthetic recording as
    scenarios/marg/mekf.py feeds it: NumPy reference (batch update, chain-rule A) == compiled step
    == compiled run, heading masked and gyro-at-rest used in parts."""
    from symkf.scenarios.marg import mekf as ekf
    from symkf.scenarios.marg.data import Recording
    rng = np.random.default_rng(11)
    n = 800                                           # 1.6 s at rest (the rest rule needs 1.5 s), then turning
    time = np.arange(n) / 285.714
    gyro = rng.normal(0.0, 2e-3, (n, 3)) + np.where(time[:, None] > 1.6, [0.3, -0.2, 0.8], 0.0)
    acc = rng.normal([0.0, 0.0, 9.81], 0.05, (n, 3))
    mag = rng.normal([0.0, 25.0, -43.0], 0.3, (n, 3))
    mag[600:650] *= 1.2                               # a disturbance: the heading is masked there
    recording = Recording("synthetic", time, gyro, acc, mag)
    z, mask = ekf.measurements(recording), ekf.masks(recording)
    assert 0 < mask[:, 3].sum() < n and 0 < mask[:, 4].sum() < n
    compiled = load("marg_mekf", backend="compiled")
    run = ekf.run_recording(compiled, recording)
    stepped = ekf.make_filter(compiled, recording)
    ref = ManifoldReference("marg_mekf", "mekf", stepped.x, stepped.P, stepped.Q)
    assert ref.transition == "series"
    stepped.update(z[0], "marg", q=mag[0], mask=mask[0], u=gyro[0])
    ref.u = gyro[0]
    ref.update(z[0], "marg", 0.0, q=mag[0], mask=mask[0])
    for k in range(1, n):
        dt = time[k] - time[k - 1]
        stepped.step(time[k - 1], dt, z[k], "marg", q=mag[k], mask=mask[k], u=gyro[k])
        ref.step(time[k - 1], dt, z[k], "marg", q=mag[k], mask=mask[k], u=gyro[k])
        np.testing.assert_allclose(run.x[k], stepped.x, rtol=0, atol=1e-14)
        np.testing.assert_allclose(run.P[k], stepped.P, rtol=0, atol=1e-18)
    _assert_close(stepped.x, ref.x, rtol=1e-10, what="x after 800 samples")
    _assert_close(stepped.P, ref.P, rtol=1e-9, what="P after 800 samples")
    assert np.max(np.abs(stepped.x[4:])) > 1e-4                # the bias moved: not a vacuous run


def test_left_and_right_charts_differ_and_the_reference_tells_them_apart(spinner, spinner_left):
    """The two sides give different covariances (a body-frame vs a reference-frame error), and the
    reference of the other side does not match: the left-chart test above checks the left chart."""
    right, left = spinner.filter("mekf", X0, P0, QPSD), spinner_left.filter("mekf", X0, P0, QPSD)
    for f in (right, left):
        f.predict(0.0, 0.02, u=U)
    ref_right = ManifoldReference(SPINNER, "mekf", X0, P0, QPSD, side="right")
    ref_right.predict(0.0, 0.02, u=U)
    assert np.max(np.abs(left.P - right.P)) > 1e-5          # ~1 % of P here; equality tests use 1e-11
    assert np.max(np.abs(left.P - ref_right.P)) > 1e-5
    _assert_close(right.P, ref_right.P, what="right predict P")


def test_manifest_records_quaternion_and_error_dimension(spinner):
    description = spinner.model
    assert description["error_state_dim"] == 5
    assert description["quaternions"][0]["name"] == "q"
    assert description["quaternions"][0]["states"] == [0, 1, 2, 3]
    assert spinner.filters["mekf"].algorithm == "manifold_ekf"
    # the run loop iterates the step without its diagnostics y, S (test_run_equals_steps_and_tracks)
    assert spinner.filters["mekf"].run == {name: f"mekf_run_{name}" for name in ("vectors", "gyro_z")}
    assert [name for name, _ in spinner.backend.kernels["mekf_run_vectors"].outputs] == ["x", "P", "status"]
    f = spinner.filter("mukf", X0, P0, QPSD)
    assert f.P.shape == (5, 5) and f.x.shape == (6,)


@pytest.mark.parametrize("family", ["mekf", "mukf"])
def test_run_equals_steps_and_tracks(spinner, family):
    rng = np.random.default_rng(4)
    n = 400
    times = np.arange(n) * 0.01
    truth = [Q0]
    for _ in range(n - 1):
        truth.append(hamilton(truth[-1], exp_rotvec(np.r_[U, 0.4] * 0.01)))
    z = np.array([_vectors(q, rng) for q in truth])
    x_start = np.r_[hamilton(Q0, exp_rotvec([0.2, -0.1, 0.3])), 0.4, 0.0]
    run_filter = spinner.filter(family, x_start, P0, QPSD)
    result = run_filter.run(times, z, "vectors", u=U)
    step_filter = spinner.filter(family, x_start, P0, QPSD)
    for k in range(n):
        if k == 0:                                  # the run's first step has dt = 0: an update
            step_filter.update(z[0], "vectors", u=U)
        else:
            step_filter.step(times[k - 1], times[k] - times[k - 1], z[k], "vectors", u=U)
        np.testing.assert_allclose(result.x[k], step_filter.x, rtol=0, atol=1e-13)
        np.testing.assert_allclose(result.P[k], step_filter.P, rtol=0, atol=1e-15)
    error = np.linalg.norm(log_quaternion(hamilton(truth[-1] * [-1, -1, -1, 1], result.x[-1, :4])))
    assert error < 0.02, f"final attitude error {np.degrees(error):.2f} deg"


def test_unit_norm_kept_over_a_million_steps(spinner):
    """Retraction and reset keep |q| = 1 to 1e-15 in the compiled run loop (10^6 MEKF steps)."""
    f = spinner.filter("mekf", X0, P0, QPSD)
    rng = np.random.default_rng(7)
    chunk, worst, t0 = 100_000, 0.0, 0.0
    z = 0.42 + rng.normal(0, 0.01, (chunk, 1))     # z gyro: its correction moves q through P's correlations
    for _ in range(10):
        times = t0 + 0.01 * np.arange(1, chunk + 1)
        result = f.run(times, z, "gyro_z", u=U)
        assert result.failed_steps.size == 0
        worst = max(worst, float(np.max(np.abs(np.linalg.norm(result.x[:, :4], axis=1) - 1))))
        t0 = times[-1]
    assert worst <= 1e-15, worst
    assert np.linalg.norm(log_quaternion(hamilton(X0[:4] * [-1, -1, -1, 1], f.x[:4]))) > 1.0   # q did move


@pytest.mark.parametrize("family", ["mekf", "mukf"])
def test_bad_input_leaves_state_unchanged(spinner, family):
    f = spinner.filter(family, X0, P0, QPSD, gate="none")          # z of zeros: off any gate
    f.predict(0.0, 0.01, u=U)
    x, P = f.x.copy(), f.P.copy()
    with pytest.raises(ValueError, match="quaternion state 'q'.*norm 2"):
        f.x = np.r_[2 * Q0, 0.4, 0.0]
    with pytest.raises(SymkfError, match="NONFINITE"):
        f.update(np.r_[np.nan, np.zeros(5)], "vectors")
    with pytest.raises(ValueError, match="P: expected shape"):
        f.P = np.eye(6)
    np.testing.assert_array_equal(f.x, x)
    np.testing.assert_array_equal(f.P, P)
    assert f.update(np.r_[np.nan, np.zeros(5)], "vectors", mask=np.r_[0, np.ones(5)]) == 0   # masked NaN is fine


def test_non_unit_quaternion_is_a_domain_error_in_c(spinner):
    """The C kernel checks |q| itself (a flight caller has no Python contract)."""
    f = spinner.filter("mekf", X0, P0, QPSD)
    f.kernel_buffer("x")[:4] = 1.1 * Q0
    with pytest.raises(SymkfError, match="DOMAIN"):
        f.predict(0.0, 0.01, u=U)
    np.testing.assert_array_equal(f.x[:4], 1.1 * Q0)


def test_quaternion_state_declaration_errors():
    m = Model("bad", "x")
    q = m.quaternion_state("q", "attitude")
    with pytest.raises(ModelError, match="declared twice"):
        m.quaternion_state("q", "again")
    with pytest.raises(ModelError, match="must be a 4-vector"):
        m.set_dynamics({"q": q[0:3]})
    assert m.nx == 4 and m.n_error == 3


def test_measurement_that_depends_on_nothing_is_refused():
    import casadi as ca
    m = Model("constant_sensor", "a quaternion and a sensor that reads a constant")
    q = m.quaternion_state("q", "attitude")
    m.set_dynamics({"q": 0 * q})
    m.measurement("blind", [("k", "-", "a constant reading", ca.SX(1.0))], sigma=[0.1])
    m.filters = ("mekf",)
    with pytest.raises(ModelError, match="measurement 'blind' does not depend on the state"):
        m.validate()


def test_initial_value_errors_are_clear(spinner):
    """Wrong sizes and a non-unit initial quaternion are refused with the rule that was broken;
    a quaternion within the tolerance is accepted and the prediction projects it onto |q| = 1."""
    with pytest.raises(ValueError, match=r"x: expected shape \(6,\), got \(5,\)"):
        spinner.filter("mekf", X0[:5], P0, QPSD)
    with pytest.raises(ValueError, match="quaternion state 'q'.*norm 1.1, expected 1 within 1e-06"):
        spinner.filter("mekf", np.r_[1.1 * Q0, X0[4:]], P0, QPSD)
    with pytest.raises(ValueError, match=r"P: expected shape \(5, 5\), got \(6, 6\)"):
        spinner.filter("mekf", X0, np.eye(6), QPSD)
    with pytest.raises(ValueError, match=r"Q: expected shape \(5, 5\)"):
        spinner.filter("mukf", X0, P0, np.eye(6))
    f = spinner.filter("mekf", np.r_[(1 + 1e-9) * Q0, X0[4:]], P0, QPSD)
    f.predict(0.0, 0.01, u=U)
    assert abs(np.linalg.norm(f.x[:4]) - 1) < 1e-15


def test_kernels_per_mask_pattern_are_generic_and_change_no_number(spinner):
    """``manifold_run_variants`` on the small quaternion model (not only marg_ekf): with component
    0 (of either measurement) and the gate folded away for steps that mask it, the run and the step
    give the numbers and codes of the build without variants, bit for bit."""
    variants = load(SPINNER, backend="compiled", manifold_run_variants=((0,),))
    kernels = variants.backend.kernels
    assert "mekf_run_vectors_masked_0" in kernels and "mekf_step_gyro_z_masked_0" in kernels
    assert "mekf_run_vectors_masked_0" not in spinner.backend.kernels
    rng = np.random.default_rng(9)
    n = 300
    times = np.arange(n) * 0.01
    z = np.array([_vectors(Q0, rng) for _ in range(n)])
    mask = np.ones((n, 6))
    mask[rng.random(n) < 0.5, 0] = 0.0
    mask[100:120, :] = 0.0                                 # every component masked
    results = []
    for compiled in (spinner, variants):
        run = compiled.filter("mekf", X0, P0, QPSD).run(times, z, "vectors", mask=mask, u=U)
        stepped = compiled.filter("mekf", X0, P0, QPSD)
        xs, codes = [], []
        for k in range(1, n):
            codes.append(stepped.step(times[k - 1], 0.01, z[k], "vectors", mask=mask[k], u=U))
            xs.append(np.r_[stepped.x, stepped.P.ravel()])
        results.append((run.x, run.P, run.status, np.array(xs), codes))
    for a, b in zip(*results):
        assert np.array_equal(a, b)

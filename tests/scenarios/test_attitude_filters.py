"""Attitude model and filters of paper 000: model equations, eigen mean, compiled == NumPy reference,
quaternion norm, the eq (41) guard and bad-input rules."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from symkf.codegen.discretize import discrete_dynamics
from symkf.codegen.spec import STATUS_DOMAIN
from symkf.models import attitude as att
from symkf.models import get_model
from symkf.runtime import SymkfError, load
from symkf.scenarios.attitude.filter import AttitudeFilter
from symkf.scenarios.attitude.reference import ReferenceAttitudeFilter, _Functions, eigen_mean

N_PROPAGATION_POINTS = 25       # 2 (6 + 6) + 1: the separated UKF's [x, w] set, the size of the mean kernel

P0 = 0.01 * np.eye(6)      # section V, scenario I


@pytest.fixture(scope="module")
def compiled():
    return load("attitude", backend="compiled")


@pytest.fixture(scope="module")
def functions():
    return _Functions.get()        # the paper's equations (models/attitude.py) as CasADi Functions


def initial_quaternion(seed=2, error_deg=10.0):
    truth = Rotation.random(random_state=seed)
    axis = np.random.default_rng(seed).normal(size=3)
    error = Rotation.from_rotvec(np.deg2rad(error_deg) * axis / np.linalg.norm(axis))
    return truth, (truth * error).as_quat()


def gyro_and_star_sequence(truth, n_steps, seed=5, star_every=4):
    """A short synthetic record (rates and noisy star-tracker quaternions; not a truth simulation)."""
    rng = np.random.default_rng(seed)
    omega = rng.normal(scale=0.01, size=(n_steps, 3))
    noisy = truth * Rotation.from_rotvec(rng.normal(scale=1e-3, size=(n_steps, 3)))
    stars = [noisy[k].as_quat() if k % star_every == star_every - 1 else None for k in range(n_steps)]
    return omega, stars


# ---------------------------------------------------------------------- model
def test_table1_values():
    assert np.allclose(att.STAR_TRACKER_SIGMA, [0.4e-3, 0.4e-3, 8.1e-3])
    assert att.GYRO_ANGLE_RANDOM_WALK == 4.36e-5 and att.GYRO_RATE_RANDOM_WALK == 2.01e-7
    assert np.allclose(np.diag(att.process_noise_psd()), [4.36e-5 ** 2] * 3 + [2.01e-7 ** 2] * 3)
    model = get_model("attitude")
    assert model.state_names() == list(att.STATE_NAMES) and model.filters == ("mekf", "sukf", "aukf")
    assert [qs.name for qs in model.quaternions] == ["q"] and model.n_error == 6


def test_closed_form_propagation_equals_integrated_kinematics(functions):
    """Eq (45) (closed form) against eqs (27)-(28) integrated by RK4 with 200 sub-steps."""
    model = get_model("attitude")
    fd = discrete_dynamics(model, 200)
    rng = np.random.default_rng(1)
    for _ in range(5):
        q, b = Rotation.random(random_state=rng.integers(1e6)).as_quat(), rng.normal(scale=1e-2, size=3)
        omega_g, eta_a = rng.normal(scale=0.05, size=3), rng.normal(scale=1e-3, size=3)
        eta_b = rng.normal(scale=1e-5, size=3)
        q_next, b_next = functions.propagate(q, b, omega_g, eta_a, eta_b, 0.25)
        x_rk4 = np.array(fd(0, 0.25, np.concatenate([q, b]), omega_g, [], np.concatenate([eta_a, eta_b]))).ravel()
        # (44) holds b_k over the step; RK4 of (27)-(28) lets b drift with η_b, so compare q with the
        # rate ω = ω_g + b + η_a held (bias state 0, same rate) and b with the full RK4 state.
        x_hold = np.array(fd(0, 0.25, np.concatenate([q, np.zeros(3)]), omega_g + b + eta_a, [], np.zeros(6))).ravel()
        assert np.allclose(np.array(q_next).ravel(), x_hold[:4], atol=1e-13)
        assert np.allclose(np.array(b_next).ravel(), x_rk4[4:], atol=1e-15)


def test_star_tracker_model_matches_scipy(functions):
    """Eq (30): q_s = δq_s ⊗ q, i.e. scipy's R(q) * R(η_s)."""
    rng = np.random.default_rng(2)
    for _ in range(10):
        truth, eta = Rotation.random(random_state=rng.integers(1e6)), rng.normal(scale=1e-2, size=3)
        q_s = np.array(functions.star_tracker(truth.as_quat(), eta)).ravel()
        assert np.allclose(q_s, (truth * Rotation.from_rotvec(eta)).as_quat(), atol=1e-15) or \
            np.allclose(-q_s, (truth * Rotation.from_rotvec(eta)).as_quat(), atol=1e-15)


# ---------------------------------------------------------------------- eigen mean
def _mean_kernel(compiled):
    n = N_PROPAGATION_POINTS
    buffers = {"quaternions": np.zeros((4, n), order="F"), "weights": np.zeros(n), "q_ref": np.zeros(4),
               "q": np.zeros(4)}
    return buffers, compiled.backend.bind(f"quaternion_mean_{n}", buffers)


@pytest.mark.parametrize("spread", [1e-6, 1e-3, 0.1, 1.0, 3.0])
@pytest.mark.parametrize("weighting", ["random", "ukf_kappa_1", "ukf_negative_center"])
def test_eigen_mean_equals_eigh(compiled, spread, weighting):
    """The C mean (no LAPACK, fixed iterations) equals numpy.linalg.eigh's eigenvector to 1e-12."""
    buffers, call = _mean_kernel(compiled)
    n = N_PROPAGATION_POINTS
    rng = np.random.default_rng(int(spread * 1e6) + len(weighting))
    for trial in range(20):
        center = Rotation.random(random_state=rng.integers(1e6))
        rotations = center * Rotation.from_rotvec(rng.normal(scale=spread, size=(n, 3)))
        quats = rotations.as_quat() * rng.choice([-1, 1], size=(n, 1))    # either sign of each q_i
        if weighting == "random":
            weights = rng.uniform(0.05, 1, n)
            weights /= weights.sum()
        else:
            kappa = 1.0 if weighting == "ukf_kappa_1" else -3.0
            weights = np.array([kappa / (12 + kappa)] + [0.5 / (12 + kappa)] * (n - 1))
        buffers["quaternions"][:] = quats.T
        buffers["weights"][:] = weights
        buffers["q_ref"][:] = center.as_quat()
        assert call() == 0
        M = (quats.T * weights) @ quats
        values, vectors = np.linalg.eigh(M)
        expected = vectors[:, -1]
        gap = (values[-1] - values[-2]) / (values[-1] - values[0])
        assert gap > 1e-6, "test set too degenerate for any eigen solver"
        assert abs(np.linalg.norm(buffers["q"]) - 1) < 1e-15
        assert min(np.abs(buffers["q"] - expected).max(), np.abs(buffers["q"] + expected).max()) < 1e-12
        assert buffers["q"] @ center.as_quat() >= 0          # sign aligned with the reference
        # the same as the reference's eigenvector of N (36) for its smallest eigenvalue
        reference = eigen_mean(quats, weights, center.as_quat())
        assert np.abs(buffers["q"] - reference).max() < 1e-12


# ---------------------------------------------------------------------- three paths, one answer
@pytest.mark.parametrize("kind", ["mekf", "ukf", "aukf"])
def test_compiled_step_equals_numpy_reference(compiled, kind):
    truth, q0 = initial_quaternion()
    omega, stars = gyro_and_star_sequence(truth, 24)
    fast = AttitudeFilter(compiled, kind, q0, np.zeros(3), P0)
    slow = ReferenceAttitudeFilter(kind, q0, np.zeros(3), P0)
    for w, q_s in zip(omega, stars):
        fast.step(w, 0.25, q_s)
        slow.step(w, 0.25, q_s)
        assert np.abs(fast.x - slow.x).max() < 1e-12
        # P falls from 1e-2 to 1e-8 by cancellation in P - K P^yy K^T: round-off is relative to P0
        assert np.abs(fast.P - slow.P).max() < 1e-14 * np.abs(P0).max()
    assert np.abs(fast.y - slow.y).max() < 1e-12
    # the estimate did move towards the star tracker (the comparison is not trivially of nothing)
    assert (Rotation.from_quat(fast.q).inv() * truth).magnitude() < np.deg2rad(1.0)


@pytest.mark.parametrize("kind", ["mekf", "ukf"])
def test_predict_update_equals_step(compiled, kind):
    truth, q0 = initial_quaternion(3)
    omega, stars = gyro_and_star_sequence(truth, 8)
    stepped = AttitudeFilter(compiled, kind, q0, np.zeros(3), P0)
    split = AttitudeFilter(compiled, kind, q0, np.zeros(3), P0)
    for w, q_s in zip(omega, stars):
        stepped.step(w, 0.25, q_s)
        split.predict(w, 0.25)
        if q_s is not None:
            split.update(q_s)
    assert np.abs(stepped.x - split.x).max() < 1e-15 and np.abs(stepped.P - split.P).max() < 1e-18


@pytest.mark.parametrize("kind", ["mekf", "ukf", "aukf"])
def test_quaternion_norm_stays_unit(compiled, kind):
    """A 20 000-step run (about 1.4 h at 0.25 s, star tracker every 1 s); the report gives 10^6 steps."""
    truth0, q0 = initial_quaternion(5, error_deg=1.0)
    rng = np.random.default_rng(6)
    n, dt = 20_000, 0.25
    rate = rng.normal(scale=0.02, size=3)
    omega = np.tile(rate, (n, 1))
    truth = truth0 * Rotation.from_rotvec(np.outer(np.arange(1, n + 1) * dt, rate))
    noisy = truth * Rotation.from_rotvec(rng.normal(size=(n, 3)) * att.STAR_TRACKER_SIGMA)
    z = np.where((np.arange(n) % 4 == 3)[:, None], noisy.as_quat(), np.nan)
    result = AttitudeFilter(compiled, kind, q0, np.zeros(3), P0).run(omega, dt, z)
    assert not result.failed_steps.size
    assert np.abs(np.linalg.norm(result.x[:, :4], axis=1) - 1).max() < 1e-12
    final_error = (Rotation.from_quat(result.x[-1, :4]).inv() * truth[-1]).magnitude()
    assert final_error < np.deg2rad(0.1)


@pytest.mark.parametrize("kind", ["mekf", "ukf", "aukf"])
def test_quaternion_norm_without_star_tracker(compiled, kind):
    """Propagation only at a constant rate, where rounding in Ω_k (45) repeats identically each step."""
    _, q0 = initial_quaternion(7, error_deg=0.0)
    n = 20_000
    omega = np.tile(np.random.default_rng(8).normal(scale=0.02, size=3), (n, 1))
    P_small = np.diag([1e-10] * 3 + [1e-16] * 3)
    result = AttitudeFilter(compiled, kind, q0, np.zeros(3), P_small).run(omega, 0.25, np.full((n, 4), np.nan))
    assert not result.failed_steps.size
    assert np.abs(np.linalg.norm(result.x[:, :4], axis=1) - 1).max() < 1e-12


# ---------------------------------------------------------------------- guards and bad input
@pytest.mark.parametrize("kind", ["ukf", "aukf"])
def test_eq41_guard_is_a_domain_error(compiled, kind):
    """P so large that γ√P > 1: |δp| >= 1 in (41) is SYMKF_ERR_DOMAIN, state unchanged, no NaN."""
    _, q0 = initial_quaternion()
    P_large = np.diag([0.2, 0.2, 0.2, 1e-4, 1e-4, 1e-4])
    filt = AttitudeFilter(compiled, kind, q0, np.zeros(3), P_large)
    x_before, P_before = filt.x.copy(), filt.P.copy()
    with pytest.raises(SymkfError) as info:
        filt.step(np.zeros(3), 0.25, None)
    assert info.value.code == STATUS_DOMAIN
    assert np.array_equal(filt.x, x_before) and np.array_equal(filt.P, P_before)
    with pytest.raises(SymkfError) as info:
        ReferenceAttitudeFilter(kind, q0, np.zeros(3), P_large).step(np.zeros(3), 0.25, None)
    assert info.value.code == STATUS_DOMAIN


@pytest.mark.parametrize("kind", ["mekf", "ukf"])
def test_non_unit_star_tracker_quaternion(compiled, kind):
    """Normalised when |q_s| is within 1e-3 of 1, rejected (SYMKF_ERR_DOMAIN) beyond."""
    truth, q0 = initial_quaternion()
    q_s = truth.as_quat()
    a = AttitudeFilter(compiled, kind, q0, np.zeros(3), P0)
    b = AttitudeFilter(compiled, kind, q0, np.zeros(3), P0)
    a.update(q_s)
    b.update(q_s * 1.0005)
    assert np.abs(a.x - b.x).max() < 1e-14
    x_before, P_before = b.x.copy(), b.P.copy()
    with pytest.raises(SymkfError) as info:
        b.update(q_s * 1.5)
    assert info.value.code == STATUS_DOMAIN
    assert np.array_equal(b.x, x_before) and np.array_equal(b.P, P_before)


def test_initial_state_and_shape_errors(compiled):
    _, q0 = initial_quaternion()
    with pytest.raises(ValueError, match="q0"):
        AttitudeFilter(compiled, "ukf", q0 * 2, np.zeros(3), P0)
    with pytest.raises(ValueError, match="P0"):
        AttitudeFilter(compiled, "ukf", q0, np.zeros(3), np.eye(7))
    with pytest.raises(ValueError, match="kind"):
        AttitudeFilter(compiled, "pf", q0, np.zeros(3), P0)
    filt = AttitudeFilter(compiled, "mekf", q0 * 1.0002, np.zeros(3), P0)
    assert abs(np.linalg.norm(filt.q) - 1) < 1e-15                 # normalised
    with pytest.raises(ValueError, match="omega_g"):
        filt.step([0, 0], 0.25)
    with pytest.raises(ValueError, match="update"):
        AttitudeFilter(compiled, "aukf", q0, np.zeros(3), P0).update(q0)

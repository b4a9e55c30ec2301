"""Paper 000 quaternion helpers (models/quaternion.py, appended part) against scipy's Rotation."""
import casadi as ca
import numpy as np
import pytest
from scipy.linalg import expm
from scipy.spatial.transform import Rotation

from symkf.models import quaternion as quat

N_RANDOM = 50


def evaluate(expression_builder, *values):
    """Evaluate a symbolic helper on numeric inputs through an SX Function (as codegen does)."""
    symbols = [ca.SX.sym(f"a{i}", np.size(v)) for i, v in enumerate(values)]
    out = expression_builder(*symbols)
    outputs = out if isinstance(out, tuple) else (out,)
    f = ca.Function("f", symbols, list(outputs))
    results = f(*[np.ravel(v) for v in values])
    if len(outputs) == 1:
        return np.array(results)
    return [np.array(r) for r in results]


def same_rotation(q1, q2, atol=1e-12):
    q1, q2 = np.ravel(q1), np.ravel(q2)
    return min(np.abs(q1 - q2).max(), np.abs(q1 + q2).max()) < atol


@pytest.fixture(scope="module")
def rotations():
    return Rotation.random(N_RANDOM, random_state=7), Rotation.random(N_RANDOM, random_state=8)


def test_paper_product_is_shuster_order(rotations):
    r1, r2 = rotations
    for a, b in zip(r1, r2):
        product = evaluate(quat.otimes, a.as_quat(), b.as_quat())
        assert same_rotation(product, (b * a).as_quat())     # eq (23): q ⊗ q' = hamilton(q', q)


def test_product_matrix_is_psi_and_q(rotations):
    """Eq (23) and (26): [q⊗] = [Ψ(q) q]."""
    for a, b in zip(*rotations):
        q, qp = a.as_quat(), b.as_quat()
        matrix = np.hstack([evaluate(quat.psi_matrix, q), q[:, None]])
        assert np.allclose(matrix @ qp, evaluate(quat.otimes, q, qp).ravel(), atol=1e-14)


def test_attitude_matrix_identities(rotations):
    """Eq (25): A(q) = Ξᵀ(q) Ψ(q) = R(q)ᵀ maps reference vectors into the body frame."""
    rng = np.random.default_rng(0)
    for a in rotations[0]:
        q, v = a.as_quat(), rng.normal(size=3)
        A = evaluate(quat.attitude_matrix, q)
        assert np.allclose(A, evaluate(quat.xi_matrix, q).T @ evaluate(quat.psi_matrix, q), atol=1e-14)
        assert np.allclose(A @ v, a.inv().apply(v), atol=1e-13)
        assert np.allclose(evaluate(quat.rotation_matrix, q) @ v, a.apply(v), atol=1e-13)


def test_inverse_and_identity(rotations):
    """Eq (23): q ⊗ q⁻¹ = q_I and q⁻¹ is scipy's inverse."""
    for a in rotations[0]:
        q = a.as_quat()
        assert np.allclose(evaluate(lambda x: quat.otimes(x, quat.conjugate(x)), q).ravel(), [0, 0, 0, 1], atol=1e-15)
        assert same_rotation(evaluate(quat.conjugate, q), a.inv().as_quat())


def test_error_quaternion_round_trip_and_eq34(rotations):
    """δq = q_i ⊗ q⁻¹ takes q to q_i; its vector part is -Ξᵀ(q_i) q (eq (34) prints Ψ: for the scalar
    weights of (36) both give N, since Ψ Ψᵀ = Ξ Ξᵀ = I - q qᵀ)."""
    for a, b in zip(*rotations):
        qi, q = a.as_quat(), b.as_quat()
        delta = evaluate(quat.error_quaternion, qi, q).ravel()
        assert same_rotation(evaluate(quat.otimes, delta, q), qi)
        assert same_rotation(delta, (b.inv() * a).as_quat())
        assert np.allclose(delta[:3], -evaluate(quat.xi_matrix, qi).T @ q, atol=1e-14)
        psi, xi = evaluate(quat.psi_matrix, qi), evaluate(quat.xi_matrix, qi)
        assert np.allclose(psi @ psi.T, xi @ xi.T, atol=1e-14)
        assert np.allclose(psi @ psi.T, np.eye(4) - np.outer(qi, qi), atol=1e-14)


def test_rotation_vector_round_trips():
    rng = np.random.default_rng(3)
    angles = np.concatenate([rng.uniform(0, np.pi - 1e-6, 40), [0.0, 1e-12, 1e-9, 1e-5, 1e-4, 2e-4]])
    for angle in angles:
        axis = rng.normal(size=3)
        v = angle * axis / np.linalg.norm(axis)
        q = evaluate(quat.rotvec_to_quaternion, v).ravel()
        assert np.allclose(q, Rotation.from_rotvec(v).as_quat(), atol=1e-15, rtol=0)
        assert np.allclose(evaluate(quat.quaternion_to_rotvec, q).ravel(), v, atol=1e-13, rtol=0)
        assert np.allclose(evaluate(quat.quaternion_to_rotvec, -q).ravel(), v, atol=1e-13, rtol=0)


def test_omega_matrix_and_discrete_propagation(rotations):
    """Eq (27): Ω(ω) q = [q_ω⊗] q; eq (45): Ω_k = expm(½ Ω(ω) dt) = scipy's body-rate rotation."""
    rng = np.random.default_rng(4)
    for a in rotations[0]:
        q, omega, dt = a.as_quat(), rng.normal(scale=0.3, size=3), 0.25
        Omega = evaluate(quat.omega_matrix, omega)
        assert np.allclose(Omega @ q, evaluate(quat.otimes, np.append(omega, 0), q).ravel(), atol=1e-15)
        Omega_k = evaluate(quat.discrete_omega_matrix, omega, dt)
        assert np.allclose(Omega_k, expm(0.5 * Omega * dt), atol=1e-14)
        assert same_rotation(Omega_k @ q, (a * Rotation.from_rotvec(omega * dt)).as_quat())
        assert np.allclose(Omega_k.T @ Omega_k, np.eye(4), atol=1e-15)


def test_discrete_propagation_regular_at_zero_rate():
    omega = ca.SX.sym("omega", 3)
    jac = ca.Function("j", [omega], [ca.jacobian(quat.discrete_omega_matrix(omega, 0.25) @ ca.DM([0, 0, 0, 1]), omega)])
    assert np.allclose(np.array(jac([0, 0, 0])), np.vstack([0.125 * np.eye(3), np.zeros(3)]), atol=1e-15)
    assert np.allclose(evaluate(quat.discrete_omega_matrix, np.zeros(3), 0.25), np.eye(4))


def test_quaternion_from_error_vector_domain():
    """Eq (41): unit quaternion inside |δp| < 1; outside, a 0 flag and finite numbers, never NaN."""
    q, ok = evaluate(quat.quaternion_from_error_vector, np.array([0.3, -0.2, 0.1]))
    assert ok == 1 and abs(np.linalg.norm(q) - 1) < 1e-15
    for bad in ([1.0, 0, 0], [0.8, 0.8, 0.0], [3.0, 0, 0]):
        q, ok = evaluate(quat.quaternion_from_error_vector, np.array(bad))
        assert ok == 0 and np.isfinite(q).all()

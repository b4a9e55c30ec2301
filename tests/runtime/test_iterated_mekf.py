"""The MEKF's iterated update (option mekf_iterations, codegen/families/mekf.py) on the spinner
model file: a tolerance never met is the plain MEKF; iterations from a large attitude error move
the estimate and keep P symmetric positive definite; the compiled iterations equal the NumPy
reference's (runtime/reference/manifold.py) to round-off, with and without a tolerance that stops
them early; an all-masked update changes nothing; the sequential update refuses the option."""
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from symkf.codegen import generate, make_config
from symkf.codegen.spec import ConfigError
from symkf.runtime import Filter, load
from symkf.runtime.reference import ManifoldReference

SPINNER = str(Path(__file__).resolve().parent.parent / "codegen" / "spinner_model.py")


@pytest.fixture(scope="module")
def builds():
    return {"plain": load(SPINNER), "iterated": load(SPINNER, mekf_iterations=4),
            "stopped": load(SPINNER, mekf_iterations=4, mekf_iteration_tolerance=1e9),
            "early": load(SPINNER, mekf_iterations=6, mekf_iteration_tolerance=0.05)}


def case():
    q_true = Rotation.from_rotvec([0.0, 0.0, 0.2]).as_quat()
    q0 = Rotation.from_rotvec([0.5, -0.4, 0.9]).as_quat()              # ~1.1 rad off
    x0 = np.r_[q0, 0.4, 0.02]
    P0 = np.diag([0.5, 0.5, 0.8, 0.01, 1e-4])
    R_t = Rotation.from_quat(q_true).as_matrix().T
    z = np.r_[R_t @ [0, 0, 1.0], R_t @ [1.0, 0, 0]]
    return x0, P0, np.diag([1e-4, 1e-4, 2e-4, 1e-3, 1e-6]), z, q_true


def angle(q, q_true):
    return np.linalg.norm((Rotation.from_quat(q) * Rotation.from_quat(q_true).inv()).as_rotvec())


def test_iterations_and_a_tolerance_never_met(builds):
    x0, P0, Q, z, q_true = case()
    f = {k: Filter(builds[k], "mekf", x0, P0, Q, gate="none") for k in builds}
    for g in f.values():
        g.update(z, "vectors")
    np.testing.assert_allclose(f["stopped"].x, f["plain"].x, rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(f["stopped"].P, f["plain"].P, rtol=1e-12, atol=1e-18)
    assert np.max(np.abs(f["iterated"].x - f["plain"].x)) > 1e-3
    assert angle(f["iterated"].x[:4], q_true) < angle(f["plain"].x[:4], q_true)
    P = f["iterated"].P
    assert np.array_equal(P, P.T) and np.all(np.linalg.eigvalsh(P) > 0)
    before = (f["iterated"].x.copy(), f["iterated"].P.copy())
    f["iterated"].update(z, "vectors", mask=np.zeros(6))
    assert np.array_equal(f["iterated"].x, before[0]) and np.array_equal(f["iterated"].P, before[1])


#: (codegen options, reference iterations, reference tolerance) of each build.
ITERATED = {"plain": (1, 0.0), "iterated": (4, 0.0), "stopped": (4, 1e9), "early": (6, 0.05)}


@pytest.mark.parametrize("build", list(ITERATED))
def test_compiled_iterations_equal_the_numpy_reference(builds, build):
    """Predict and iterated update, three steps from a 1.1 rad attitude error: x within 1e-12 and P
    within 1e-11 relative; the iterations moved the estimate away from the plain MEKF's."""
    x0, P0, Q, z, _ = case()
    iterations, tolerance = ITERATED[build]
    f = Filter(builds[build], "mekf", x0, P0, Q, gate="none")
    ref = ManifoldReference(SPINNER, "mekf", x0, P0, Q, iterations=iterations, iteration_tolerance=tolerance)
    plain = ManifoldReference(SPINNER, "mekf", x0, P0, Q, iterations=1)
    u = np.array([0.3, -0.2])
    for k in range(3):
        f.step(None, 0.05, z, "vectors", u=u)
        ref.step(0.05 * k, 0.05, z, "vectors", u=u)
        plain.step(0.05 * k, 0.05, z, "vectors", u=u)
        np.testing.assert_allclose(f.x, ref.x, rtol=0, atol=1e-12)
        np.testing.assert_allclose(f.P, ref.P, rtol=1e-11, atol=1e-16)
    moved = np.max(np.abs(ref.x - plain.x))
    assert moved > 1e-3 if build in ("iterated", "early") else moved == 0.0


def test_sequential_update_refuses_iterations():
    with pytest.raises(ConfigError, match="mekf_iterations"):
        generate(SPINNER, make_config(SPINNER, mekf_iterations=3, manifold_update="sequential"))

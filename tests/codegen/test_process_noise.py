"""Non-additive process noise: a model with noise() gets Q = PSD of w (nw x nw),
mapped through G = df/dw at the step start: Q_d = G Q G^T dt, checked against a hand-derived G."""
import numpy as np
import pytest

from symkf.runtime import load
from symkf.runtime.reference import ReferenceFilter

GUSTY = '''
from symkf.models import Model


def build():
    m = Model("gusty", "cart pushed by a gust whose effect grows with position")
    pos, vel = m.state("pos", "m", "position"), m.state("vel", "m/s", "velocity")
    gust = m.noise("gust", "m/s^2", "gust acceleration (white)")
    m.set_dynamics({"pos": vel, "vel": -0.1 * vel + (1 + 0.5 * pos**2) * gust})
    m.measurement("gps", [("pos", "m", "position", pos)], sigma=[0.5])
    return m
'''
X0, P0, DT, PSD = np.array([2.0, 1.0]), np.diag([0.3, 0.2]), 0.1, 0.04


@pytest.fixture(scope="module")
def gusty(tmp_path_factory):
    path = tmp_path_factory.mktemp("user") / "gusty.py"
    path.write_text(GUSTY)
    return str(path), load(str(path))


@pytest.mark.parametrize("family", ["ekf", "ukf"])
def test_noise_enters_through_G_Q_GT_dt(gusty, family):
    """G = df/dw = [0, 1 + pos^2 / 2] at the step start (pos = 2: G = [0, 3])."""
    _, compiled = gusty
    with_noise, without = compiled.filter(family, X0, P0, [[PSD]]), compiled.filter(family, X0, P0, [[0.0]])
    for f in (with_noise, without):
        f.predict(0.0, DT)
    G = np.array([[0.0], [1 + 0.5 * X0[0] ** 2]])
    np.testing.assert_allclose(with_noise.P - without.P, G @ [[PSD]] @ G.T * DT, rtol=1e-12, atol=1e-15)
    np.testing.assert_array_equal(with_noise.x, without.x)          # the mean is propagated with w = 0


@pytest.mark.parametrize("family", ["ekf", "ukf"])
def test_compiled_equals_numpy_reference_with_noise(gusty, family):
    path, compiled = gusty
    compiled_filter = compiled.filter(family, X0, P0, [[PSD]])
    reference = ReferenceFilter(path, family, X0, P0, [[PSD]])
    for k in range(4):
        compiled_filter.step(DT * k, DT, [2.1 + 0.1 * k])
        reference.predict(DT * k, DT)
        reference.update([2.1 + 0.1 * k], "gps", DT * (k + 1), np.zeros(0))
    np.testing.assert_allclose(compiled_filter.x, reference.x, rtol=1e-12)
    np.testing.assert_allclose(compiled_filter.P, reference.P, rtol=1e-10, atol=1e-15)


def test_Q_is_the_noise_psd_and_the_header_states_the_discretisation(gusty):
    _, compiled = gusty
    with pytest.raises(ValueError, match=r"Q: expected shape \(1, 1\)"):
        compiled.ekf(X0, P0, np.eye(2))
    header = (compiled.backend.library_path.parent / "gusty.h").read_text()
    assert "process noise G Q G^T dt, G = df/dw at the step start" in header
    assert "power spectral density of the process noises w ['gust']" in header


def test_model_without_noise_keeps_additive_n_by_n_Q(launcher_compiled):
    doc = launcher_compiled.backend.manifest["kernels"]
    predict = next(k for k in doc if k["name"] == "ekf_predict")
    assert next(a for a in predict["inputs"] if a["name"] == "Q")["shape"] == [6, 6]
    assert "process noise Q dt" in predict["doc"]

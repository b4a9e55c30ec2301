"""The iterated EKF update (codegen/families/iterated.py, option ekf_iterations): compiled equals
its NumPy reference; a huge tolerance stops after one linearisation (the EKF); on a large initial
error (the launcher's radar is strongly nonlinear there) the iterations move the estimate."""
import copy

import numpy as np
import pytest

from symkf.codegen import generate, make_config
from symkf.codegen.spec import ConfigError
from symkf.models import get_model
from symkf.models import launcher as L
from symkf.runtime import Filter, load
from symkf.runtime.reference import ReferenceFilter


def launcher_ekf():
    model = copy.copy(get_model("launcher"))
    model.name, model.filters = "launcher_iekf", ("ekf",)
    return model


@pytest.fixture(scope="module")
def builds():
    model = launcher_ekf()
    return {"plain": load(model), "iterated": load(model, ekf_iterations=4),
            "stopped": load(model, ekf_iterations=4, ekf_iteration_tolerance=1e9)}


def record():
    """A large initial error (the campaign's 'large' case scaled up) and radar 1 at 20 Hz."""
    x_true = L.initial_state()
    dx = np.array([100.0, 0.02, 0.02, 5e3, 2e-4, 2e-4])
    ref = ReferenceFilter(launcher_ekf(), "ekf", x_true, np.eye(6), np.eye(6))
    q, rng, out = L.station_params(1), np.random.default_rng(5), []
    for k in range(8):
        t = 10.0 + 0.05 * k
        x_true = ref._fd(t, 0.05, x_true)
        out.append((t, 0.05, ref._h("radar", t + 0.05, x_true, q) + rng.normal(0, [10, 1e-4, 1e-4]), q, x_true))
    x0 = L.initial_state() + dx
    return x0, np.diag(dx**2), np.diag([1.0, 1e-8, 1e-8, 1.0, 1e-14, 1e-14]), out


def test_iterated_compiled_equals_reference_and_moves_the_estimate(builds):
    x0, P0, Q, steps = record()
    f = Filter(builds["iterated"], "ekf", x0, P0, Q, t0=10.0, gate="none")
    plain = Filter(builds["plain"], "ekf", x0, P0, Q, t0=10.0, gate="none")
    ref = ReferenceFilter(launcher_ekf(), "ekf", x0, P0, Q, ekf_iterations=4)
    for t, dt, z, q, _ in steps:
        f.step(t, dt, z, "radar", q=q)
        plain.step(t, dt, z, "radar", q=q)
        ref.step(t, dt, z, "radar", q)
        sigma = np.sqrt(np.diag(ref.P))
        assert np.max(np.abs(f.x - ref.x) / sigma) < 1e-7
        assert np.max(np.abs(f.P - ref.P) / np.outer(sigma, sigma)) < 1e-7
    assert np.max(np.abs(f.x - plain.x) / np.sqrt(np.diag(plain.P))) > 1e-3       # the iterations did something


def test_a_tolerance_never_met_is_the_plain_ekf(builds):
    x0, P0, Q, steps = record()
    f, g = (Filter(builds[k], "ekf", x0, P0, Q, t0=10.0, gate="none") for k in ("stopped", "plain"))
    for t, dt, z, q, _ in steps:
        f.step(t, dt, z, "radar", q=q)
        g.step(t, dt, z, "radar", q=q)
    np.testing.assert_allclose(f.x, g.x, rtol=1e-13)
    np.testing.assert_allclose(f.P, g.P, rtol=1e-10, atol=1e-30)


def test_bad_iteration_options_are_refused():
    with pytest.raises(ConfigError, match="ekf_iterations"):
        generate(launcher_ekf(), make_config(launcher_ekf(), ekf_iterations=0))

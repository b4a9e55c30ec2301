"""Parameters estimated by declaration (models/estimation.py, runtime/estimated.py): the cart
model marks its drag coefficient estimated; the generator carries it as a third state (its
Jacobians derived by CasADi), the runtime fills x0, P0, Q from the declaration and reports the
estimate and sigma by name. A truth with 5 % more drag: estimating it brings the velocity error
down and the estimate to within 3 sigma of the truth; the NumPy reference agrees."""
from pathlib import Path

import numpy as np
import pytest

from symkf.models import get_model
from symkf.models.errors import ModelError
from symkf.models.estimation import augmented, estimate
from symkf.runtime import Filter, estimated, load
from symkf.runtime.reference import ReferenceFilter

CART = str(Path(__file__).resolve().parent.parent / "models" / "cart_drag_model.py")
TRUE_DRAG, FORCE = 0.105, 2.0


def truth(n=400, dt=0.1, seed=0):
    rng = np.random.default_rng(seed)
    x, out, z = np.array([0.0, 0.0]), [], []
    for _ in range(n):
        for _ in range(10):                                  # fine Euler steps of the true dynamics
            x = x + dt / 10 * np.array([x[1], FORCE - TRUE_DRAG * x[1]])
        out.append(x.copy())
        z.append([x[0] + rng.normal(0, 0.5)])
    return dt * np.arange(1, n + 1), np.array(out), np.array(z)


@pytest.fixture(scope="module")
def compiled():
    return load(CART)


def test_the_generator_augments_the_state(compiled):
    model = augmented(get_model(CART))
    assert [v.name for v in model.states] == ["pos", "vel", "drag"] and not model.params
    assert compiled.model["states"][2]["name"] == "drag" and not compiled.model["params"]
    (record,) = estimated.declared(compiled)
    assert record == {"name": "drag", "initial": 0.1, "sigma": 0.02, "random_walk": 0.0, "state": 2, "q_index": 2}


@pytest.mark.parametrize("family", ["ekf", "srukf"])
def test_estimating_the_drag_fixes_a_5_percent_mismatch(compiled, family):
    times, x_true, z = truth()
    x0, P0, Q = estimated.augment(compiled, [0.0, 0.0], np.diag([1.0, 0.1]), np.diag([1e-4, 1e-4]))
    assert x0.tolist() == [0.0, 0.0, 0.1] and P0[2, 2] == pytest.approx(4e-4) and Q[2, 2] == 0.0
    f = Filter(compiled, family, x0, P0, Q)
    fixed = Filter(compiled, family, x0, np.diag([1.0, 0.1, 0.0]), Q)          # sigma 0: the drag held at 0.1
    runs = [g.run(np.r_[0.0, times], np.vstack([z[:1], z]), "gps", mask=np.r_[[[0.0]], np.ones((len(z), 1))])
            for g in (f, fixed)]
    value, sigma = estimated.report(f)["drag"]
    assert abs(value - TRUE_DRAG) < 3 * sigma and sigma < 0.005
    assert estimated.report(fixed)["drag"] == pytest.approx((0.1, 0.0), abs=1e-12)    # (the SR-UKF: round-off)
    late = slice(len(times) // 2, None)
    rms = [np.sqrt(np.mean((r.x[1:][late, 1] - x_true[late, 1]) ** 2)) for r in runs]
    assert rms[0] < 0.5 * rms[1], rms


def test_reference_agrees(compiled):
    times, _, z = truth(40)
    x0, P0, Q = estimated.augment(compiled, [0.0, 0.0], np.diag([1.0, 0.1]), np.diag([1e-4, 1e-4]))
    f = Filter(compiled, "ekf", x0, P0, Q)
    ref = ReferenceFilter(CART, "ekf", x0, P0, Q)
    f.t = 0.0
    for k in range(len(times)):
        f.step(f.t, 0.1, z[k], "gps")
        ref.step(0.1 * k, 0.1, z[k], "gps", np.zeros(0))
    np.testing.assert_allclose(f.x, ref.x, rtol=1e-10)
    np.testing.assert_allclose(f.P, ref.P, rtol=1e-8, atol=1e-14)


def test_bad_declarations_are_refused():
    model = get_model(CART)
    with pytest.raises(ModelError, match="no parameter 'mass'"):
        estimate(model, "mass", sigma=1.0)
    with pytest.raises(ModelError, match="sigma > 0"):
        estimate(model, "drag", sigma=0.0)


@pytest.mark.slow
def test_launcher_with_a_5_percent_thrust_mismatch():
    """scenarios/launcher/estimated_thrust.py, one run: the model as it is loses the flight in
    stage 2; with the mass flow estimated the errors are those of a correct model."""
    from symkf.scenarios.launcher.estimated_thrust import MISMATCH, table
    result = table(1)
    for family in ("ekf", "ukf"):
        wrong, fixed = result[family]["model as is"], result[family]["estimated"]
        assert wrong["V_final_m_s"] > 100 and fixed["V_final_m_s"] < 0.1, result[family]
        assert fixed["r_rms_m"] < 1.0 and fixed["failed_steps"] == 0
        assert abs(fixed["factor_mean"] - MISMATCH) < 3 * fixed["factor_sigma_mean"] + 1e-4

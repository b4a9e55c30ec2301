"""Authoring mistakes are refused with one line naming model, equation and symbol, at validate()
(or, for a rule that depends on the filter families, when codegen generates): none passes
silently, ends as a C compile error or as a traceback in codegen."""
import math

import casadi as ca
import pytest

from symkf.codegen import generate
from symkf.models import Model, ModelError, get_model


def cart(dynamics=None, measure=None, sigma=(1.0,), allow=(), noise=False, param=False, q=False, **meas_kw):
    """A two-state cart; ``dynamics(pos, vel, extra)`` / ``measure(pos, vel)`` override one equation."""
    m = Model("cart", "test cart")
    pos, vel = m.state("pos", "m", "position"), m.state("vel", "m/s", "velocity")
    extra = {}
    if noise:
        extra["w"] = m.noise("gust", "m/s^2", "wind gust")
    if param:
        extra["k"] = m.param("drag", "1/s", "drag coefficient", 0.1)
    m.set_dynamics(dynamics(pos, vel, extra) if dynamics else {"pos": vel, "vel": -0.1 * vel},
                   allow_nondifferentiable=allow)
    if q:
        m.measurement_params("gps", [("bias", "m", "receiver bias")])
    m.measurement("gps", [("pos", "m", "position", measure(pos, vel) if measure else pos)], sigma=sigma, **meas_kw)
    return m


@pytest.mark.parametrize("op", [ca.floor, ca.sign, ca.fabs, lambda v: ca.if_else(v > 0, v, 0)])
def test_nondifferentiable_operation_on_a_state_is_refused(op):
    with pytest.raises(ModelError, match=r"model 'cart': dvel/dt applies .* to state 'vel'") as info:
        cart(lambda pos, vel, e: {"pos": vel, "vel": -op(vel)}).validate()
    assert "\n" not in str(info.value) and "allow_nondifferentiable" in str(info.value)


def test_nondifferentiable_operation_allowed_when_marked_or_not_on_a_state():
    cart(lambda pos, vel, e: {"pos": vel, "vel": -ca.sign(vel)}, allow=["vel"]).validate()
    cart(measure=lambda pos, vel: ca.fabs(pos), allow_nondifferentiable=True).validate()
    cart(lambda pos, vel, e: {"pos": vel, "vel": -vel * ca.floor(e["k"])}, param=True).validate()
    with pytest.raises(ModelError, match="measurement 'gps' component 'pos' applies fabs to state 'pos'"):
        cart(measure=lambda pos, vel: ca.fabs(pos)).validate()


@pytest.mark.parametrize("sigma", [0.0, -1.0, math.nan])
def test_sigma_must_be_positive(sigma):
    with pytest.raises(ModelError, match=f"model 'cart': measurement 'gps' component 'pos': sigma {sigma}"):
        cart(sigma=(sigma,))


@pytest.mark.parametrize("value", [math.nan, math.inf])
def test_nonfinite_constant_is_refused(value):
    with pytest.raises(ModelError, match=f"model 'cart': dvel/dt contains the constant {value}"):
        cart(lambda pos, vel, e: {"pos": vel, "vel": value * vel}).validate()


def test_unused_noise_parameter_and_measurement_parameter_are_refused():
    with pytest.raises(ModelError, match="model 'cart': noise 'gust' is declared but the dynamics do not use it"):
        cart(noise=True).validate()
    with pytest.raises(ModelError, match="model 'cart': parameter 'drag' is declared but no equation uses it"):
        generate(cart(param=True))          # codegen knows the EKF and UKF read parameters through f, h only
    with pytest.raises(ModelError, match="measurement 'gps' parameter 'bias' is declared but not used"):
        cart(q=True).validate()


def test_vector_measurement_component_is_refused():
    with pytest.raises(ModelError, match=r"measurement 'gps' component 'pos' has shape \(2, 1\), expected a scalar"):
        cart(measure=lambda pos, vel: ca.vertcat(pos, vel))


@pytest.mark.parametrize("value, kind", [(ca.MX.sym("v"), "CasADi MX"), ([1.0, 2.0], "list"), ("vel", "string")])
def test_mx_list_or_string_expression_is_refused(value, kind):
    with pytest.raises(ModelError, match=f"model 'cart': dvel/dt is a {kind}"):
        cart(lambda pos, vel, e: {"pos": vel, "vel": value})


@pytest.mark.parametrize("body, message", [("return None", "build\\(\\) returned None"),
                                           ("return 42", "build\\(\\) returned a int, expected a symkf Model"),
                                           ("pass\nbuild = 3", "defines no build\\(\\)")])
def test_build_returning_none_or_not_a_model(tmp_path, body, message):
    path = tmp_path / "bad.py"
    path.write_text(f"def build():\n    {body}\n")
    with pytest.raises(ModelError, match=message):
        get_model(str(path))


def test_generated_name_collision_is_refused():
    """Measurements gps and gps_run would both give cart_ekf_step_gps_run: refused at generate time."""
    from symkf.codegen import BuildError, generate
    m = cart()
    m.measurement("gps_run", [("p2", "m", "position again", m.x[0])], sigma=[1.0])
    with pytest.raises(BuildError, match=r"C function cart_ekf_step_gps_run would come from both kernel "
                                         r"'ekf_step_gps' \(measurement 'gps'\) and kernel 'ekf_step_gps_run' "
                                         r"\(measurement 'gps_run'\); rename one of the measurements"):
        generate(m)


def test_model_name_must_be_a_c_identifier():
    m = cart()
    m.name = "my-cart"
    with pytest.raises(ModelError, match="model name 'my-cart' must be a C identifier"):
        m.validate()


def test_cli_reports_an_authoring_mistake_in_one_line(tmp_path, capsys):
    from symkf.scenarios.cli import main
    path = tmp_path / "bad.py"
    path.write_text("def build():\n    return None\n")
    assert main(["build", str(path)]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("symkf build:") and "returned None" in err and "\n" not in err

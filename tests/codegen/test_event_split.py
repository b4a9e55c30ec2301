"""Events the integrator respects: a step across a model event equals two steps
meeting at it, in the CasADi functions and in the generated C; split steps follow the truth."""
import casadi as ca
import numpy as np
import pytest

from symkf.codegen import make_config
from symkf.codegen.discretize import discrete_dynamics
from symkf.codegen.model_functions import ModelFunctions
from symkf.models import get_model
from symkf.models.base import Model
from symkf.models.errors import ModelError
from symkf.scenarios.launcher.truth import propagate


def _switch_model(events=(1.0,)) -> Model:
    """dx/dt = 0 before t = 1 s, 1 after (right-continuous), dy/dt = x."""
    m = Model("step_input", "a unit step in the rate at t = 1 s")
    x = m.state("x", "-", "ramp")
    y = m.state("y", "-", "integral of the ramp")
    m.set_dynamics({"x": ca.if_else(m.t >= 1.0, 1.0, 0.0), "y": x})
    m.measurement("y", [("y", "-", "the integral, measured", y)], sigma=[1.0])      # a model needs one
    m.events = events
    return m.validate()


@pytest.mark.parametrize("t, dt", [(0.5, 1.0), (0.9, 0.1), (1.0, 0.5), (0.0, 0.3)])
def test_split_step_is_exact_on_a_step_input(t, dt):
    fd = discrete_dynamics(_switch_model(), 1)
    x = np.array(fd(t, dt, [0.0, 0.0], [], [], [])).ravel()
    ramp = max(0.0, t + dt - max(t, 1.0))
    np.testing.assert_allclose(x, [ramp, ramp**2 / 2], atol=1e-5)   # 1e-6 s inset before the event


def test_unsplit_step_straddles_the_event():
    fd = discrete_dynamics(_switch_model(), 1, split_events=False)
    x = np.array(fd(0.5, 1.0, [0.0, 0.0], [], [], [])).ravel()
    assert abs(x[0] - 0.5) > 0.1          # RK4 samples the switch at stages, not where it is


def test_events_must_increase():
    with pytest.raises(ModelError, match="strictly increasing"):
        _switch_model(events=(2.0, 1.0))


@pytest.fixture(scope="module")
def functions():
    model = get_model("launcher")
    return model, ModelFunctions(model, make_config("launcher")), ModelFunctions(model, make_config("launcher", split_events=False))


@pytest.mark.parametrize("t, dt, thrust_switch", [(130.97, 0.05, True), (130.95, 0.1, True), (153.85, 0.1, False),
                                                  (360.96, 0.1, True)])
def test_launcher_step_across_an_event_equals_two_steps_meeting_at_it(functions, t, dt, thrust_switch):
    model, split, unsplit = functions
    p, u = np.array(model.param_defaults), np.zeros(0)
    x = propagate(np.array([t]))[0]
    event = min(e for e in model.events if e > t)
    one = np.array(split.fd(t, dt, x, u, p)).ravel()
    half = np.array(split.fd(t, event - t, x, u, p)).ravel()
    two = np.array(split.fd(event, t + dt - event, half, u, p)).ravel()
    np.testing.assert_allclose(one, two, rtol=1e-13, atol=0)
    truth = propagate(np.array([t, t + dt]))[1]
    old = np.array(unsplit.fd(t, dt, x, u, p)).ravel()
    assert abs(one[0] - truth[0]) < 1e-6 and abs(one[3] - truth[3]) < 1e-3   # V m/s, r m
    if thrust_switch:      # an unsplit RK4 step across a thrust switch is off by metres per second
        assert abs(old[0] - truth[0]) > 0.5 and abs(old[3] - truth[3]) > 5e-3


def test_compiled_step_across_an_event_equals_two_steps(launcher_compiled):
    """The generated C splits too: fd from the library, across stage-1 burnout."""
    model = get_model("launcher")
    p, u = np.array(model.param_defaults), np.zeros(0)
    x = propagate(np.array([130.95]))[0]
    buffers = {"t": np.zeros(1), "dt": np.zeros(1), "x": np.zeros(6), "u": u, "p": p}
    fd = launcher_compiled.backend.bind("fd", buffers)      # x in and out share one buffer

    def step(t, dt, state):
        buffers["t"][0], buffers["dt"][0], buffers["x"][:] = t, dt, state
        assert fd() == 0
        return buffers["x"].copy()

    one = step(130.95, 0.1, x)
    two = step(131.0, 0.05, step(130.95, 0.05, x))
    np.testing.assert_allclose(one, two, rtol=1e-13, atol=0)
    assert abs(one[0] - propagate(np.array([131.05]))[0][0]) < 1e-6


# ---------------------------------------------------------------------- per-filter discretisation
PAPER_LIKE = {"ekf_integrator": "euler", "ekf_covariance": "linear", "split_events": False}


def test_euler_with_linear_covariance_is_x_plus_f_dt_and_identity_plus_a_dt(functions):
    model = functions[0]
    fns = ModelFunctions(model, make_config("launcher", **PAPER_LIKE))
    ekf, ukf = fns.for_filter("ekf"), fns.for_filter("ukf")
    p, u = np.array(model.param_defaults), np.zeros(0)
    t, dt = 50.0, 0.1
    x = propagate(np.array([t]))[0]
    f = ca.Function("f", [model.t, model.x, model.p], [model.f])
    A = ca.Function("A", [model.t, model.x, model.p], [ca.jacobian(model.f, model.x)])
    x_next, F = (np.array(v) for v in ekf.fd_and_jac(t, dt, x, u, p))
    np.testing.assert_allclose(x_next.ravel(), x + dt * np.array(f(t, x, p)).ravel(), rtol=1e-14)
    np.testing.assert_allclose(F, np.eye(6) + dt * np.array(A(t, x, p)), rtol=1e-12, atol=1e-18)
    rk4 = np.array(ukf.fd(t, dt, x, u, p)).ravel()           # the UKF keeps RK4
    np.testing.assert_allclose(rk4, propagate(np.array([t, t + dt]))[1], rtol=1e-9)


@pytest.mark.parametrize("bad", [{"ekf_integrator": "rk45"}, {"ukf_covariance": "exact"}, {"ekf_substeps": 0},
                                 {"ekf_substeps": 1.5}])
def test_bad_discretisation_is_refused(bad):
    from symkf.codegen.model_functions import Discretisation
    family = next(iter(bad)).split("_")[0]
    with pytest.raises(ValueError, match=family):
        Discretisation.for_family(make_config("launcher", **bad), family)


@pytest.mark.parametrize("family", ["ekf", "ukf"])
def test_paper_like_compiled_step_equals_numpy_reference(family):
    """Each configuration builds into its own folder; its filters match the NumPy reference."""
    from symkf.runtime import load
    from symkf.runtime.reference import ReferenceFilter
    from symkf.scenarios.launcher.truth import radar_track
    paper_like = load("launcher", backend="compiled", **PAPER_LIKE)
    times = np.arange(41) * 0.1 + 128.0                    # across stage-1 burnout at 131 s
    truth = propagate(times)
    track = radar_track(times, truth)
    z, q = track.noisy(np.random.default_rng(3)), track.station_params()
    P0 = np.diag([1.0, 1e-4, 1e-4, 100.0, 1e-5, 1e-5]) ** 2
    Q = np.diag([0.005, 1e-12, 1e-12, 0.005, 1e-16, 1e-16])
    compiled = paper_like.filter(family, truth[0], P0, Q, t0=times[0])
    reference = ReferenceFilter("launcher", family, truth[0], P0, Q, **PAPER_LIKE)
    for k in range(1, len(times)):
        compiled.step(times[k - 1], 0.1, z[k], "radar", q=q[k])
        reference.step(times[k - 1], 0.1, z[k], "radar", q[k])
        sigma = np.sqrt(np.diag(reference.P))
        assert np.max(np.abs(compiled.x - reference.x) / sigma) < 1e-7

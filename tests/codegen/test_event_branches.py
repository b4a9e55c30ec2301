"""The branching event split: a step that holds no event integrates once, one that holds
an event twice, and the numbers are those of the branch-free split of main 32a5243.

``data/launcher_events_32a5243.npz`` was recorded on 32a5243 (before branching) from the compiled
library: the launcher EKF and UKF over 6 s around stage-1 burnout (radar, steps straddling
131 s) and around stage-2 ignition (radar_wgs84, a step ending exactly at 361 s), and f_d and
F = df_d/dx at seven (t, dt), four of them across an event.
"""
from pathlib import Path

import casadi as ca
import numpy as np
import pytest

from symkf.codegen import make_config
from symkf.codegen.discretize import EventBranches, event_in_step
from symkf.codegen.model_functions import ModelFunctions
from symkf.models import get_model
from symkf.scenarios.launcher.campaign import TUNING
from symkf.scenarios.launcher.truth import propagate

REFERENCE = np.load(Path(__file__).parent / "data" / "launcher_events_32a5243.npz")
RUNS = ("ekf_radar", "ukf_radar", "ekf_radar_wgs84", "ukf_radar_wgs84")


@pytest.fixture(scope="module")
def launcher_functions():
    from symkf.codegen.families.framework import FAMILIES
    from symkf.codegen.model_functions import Symbols
    model = get_model("launcher")
    fns = ModelFunctions(model, make_config("launcher"))
    FAMILIES["ukf"](model, Symbols(model), fns)         # declares the UKF's sigma-point f_d
    return model, fns


@pytest.mark.parametrize("t, dt, expected", [(130.9, 0.05, 0), (130.95, 0.05, 1), (130.97, 0.05, 1),
                                             (131.0, 0.05, 0), (50.0, 0.05, 0), (434.25, 0.1, 1)])
def test_event_flag_marks_steps_holding_an_event(t, dt, expected):
    events = get_model("launcher").events
    assert float(ca.evalf(event_in_step(ca.DM(t), ca.DM(dt), events))) == expected


def test_only_event_models_branch(launcher_functions):
    model, fns = launcher_functions
    assert len(EventBranches(model, 1).branches) == 2
    assert len(EventBranches(model, 1, split_events=False).branches) == 1
    sigma = [f for name, f in fns.for_filter("ukf").point_functions.items()
             if name in (("sigma", False), ("sigma_centre_free", True))]
    assert len(sigma) == 2, "the UKF family propagates its sigma points through fd_at_points('sigma', ...)"
    for function in (fns.fd, fns.fd_and_jac, *sigma):
        calls = [function.instruction_MX(k).which_function() for k in range(function.n_instructions())
                 if function.instruction_id(k) == ca.OP_CALL]
        assert [c.class_name() for c in calls] == ["Switch"]       # the C calls one branch per step


def test_fd_and_jacobian_equal_the_branch_free_split(launcher_functions):
    """Plain steps and steps across an event: x(t + dt) to 1e-15, F to 1e-12 relative."""
    model, fns = launcher_functions
    p = np.array(model.param_defaults)
    for (t, dt), x_ref, F_ref in zip(REFERENCE["fd_points"], REFERENCE["fd_x"], REFERENCE["fd_F"]):
        x = propagate(np.array([t]))[0]
        x_next, F = (np.array(v) for v in fns.fd_and_jac(t, dt, x, [], p))
        np.testing.assert_allclose(x_next.ravel(), x_ref, rtol=1e-15, atol=0)
        np.testing.assert_allclose(F, F_ref, rtol=1e-12, atol=1e-14 * np.abs(F_ref).max())
        np.testing.assert_array_equal(np.array(fns.fd(t, dt, x, [], p)).ravel(), x_next.ravel())
        np.testing.assert_array_equal(np.array(fns.jac_fd(t, dt, x, [], p)), F)


@pytest.fixture(scope="module")
def scalar_sigma_points():
    """The library with the UKF's sigma points one at a time (no SIMD lanes, whose libmvec round-off
    tests/codegen/test_ukf_lanes.py checks): the scalar code that was recorded."""
    from symkf.runtime import load
    return load("launcher", backend="compiled", ukf_lanes=False)


@pytest.mark.parametrize("run", RUNS)
def test_compiled_filters_equal_main_before_branching(launcher_compiled, scalar_sigma_points, run):
    """Whole runs through an event, compiled: x and P equal the recorded runs of the branch-free
    generator to 1e-12 relative (recorded ungated, from the record's first time)."""
    family, measurement = run.split("_", 1)
    f = (scalar_sigma_points if family == "ukf" else launcher_compiled).filter(family, REFERENCE[run + "_x0"], REFERENCE[run + "_P0"], TUNING["Q"], gate="none",
                                 t0=REFERENCE[run + "_times"][0], **({"kappa": 0.0} if family == "ukf" else {}))
    result = f.run(REFERENCE[run + "_times"], REFERENCE[run + "_z"], measurement=measurement, q=REFERENCE[run + "_q"])
    assert np.all(np.asarray(result.status) == 0)
    np.testing.assert_allclose(result.x, REFERENCE[run + "_x"], rtol=1e-12, atol=0)
    P_ref = REFERENCE[run + "_P"]
    scale = np.sqrt(np.einsum("kii,kjj->kij", P_ref, P_ref))        # sigma_i sigma_j
    assert np.max(np.abs(np.asarray(result.P) - P_ref) / scale) <= 1e-12

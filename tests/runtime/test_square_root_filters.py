"""The square-root filters (codegen/families/srukf.py, srekf.py) are the UKF and the EKF.

On the launcher (paper 004, radar) and on a LEO orbit-determination model with non-additive
process noise (tests/models/leo_od_model.py): the square-root UKF equals the UKF and the
square-root EKF equals the EKF in double, the compiled step equals the NumPy reference
(runtime/reference/square_root.py) and the CasADi VM, a run equals its steps bit for bit; the
carried factor is lower triangular with L L^T = P; masks, gates, a bad factor and a singular P0
behave as for every filter.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from symkf.codegen.spec import STATUS_GATED, STATUS_NOT_PD
from symkf.models import launcher as L
from symkf.runtime import Filter, SymkfError, load
from symkf.runtime.reference import ReferenceFilter, SquareRootReference

HERE = Path(__file__).resolve().parent.parent / "models"
LAUNCHER = str(HERE / "launcher_square_root_model.py")
LEO = str(HERE / "leo_od_model.py")
sys.path.insert(0, str(HERE))
import leo_od_model as leo  # noqa: E402
from compiled_cases import compiled_cases  # noqa: E402

PAIRS = (("srukf", "ukf"), ("srekf", "ekf"))


def launcher_case():
    x0 = L.initial_state() + np.array([5.0, 1e-4, 1e-4, 500.0, 1e-6, 1e-6])
    P0 = np.diag([10.0, 1e-3, 1e-3, 1e3, 1e-5, 1e-5]) ** 2
    Q = np.diag([1.0, 1e-8, 1e-8, 1.0, 1e-14, 1e-14])
    q = L.station_params(1)
    truth = ReferenceFilter(LAUNCHER, "ekf", x0, P0, Q)
    rng = np.random.default_rng(3)
    x, record = L.initial_state(), []
    for k in range(12):
        t = 10.0 + 0.05 * k
        x = truth._fd(t, 0.05, x)
        record.append((t, 0.05, truth._h("radar", t + 0.05, x, q) + rng.normal(0, [10, 1e-4, 1e-4]), q))
    return dict(model=LAUNCHER, x0=x0, P0=P0, Q=Q, measurement="radar", record=record)


def leo_case():
    x_true = leo.initial_orbit()
    x0 = x_true + np.array([300.0, -200.0, 100.0, 0.3, -0.2, 0.1])
    P0 = np.diag([500.0] * 3 + [0.5] * 3) ** 2
    Q = np.eye(3) * 1e-8
    ref = ReferenceFilter(LEO, "ekf", x0, P0, Q)
    _, z, mask = leo.simulate(lambda t, dt, x: ref._fd(t, dt, x), lambda t, x: ref._h("tracking", t, x, np.zeros(0)),
                              x_true, 10.0, 12, np.random.default_rng(4), substeps=2)
    record = [(10.0 * k, 10.0, z[k], None) for k in range(12)]
    return dict(model=LEO, x0=x0, P0=P0, Q=Q, measurement="tracking", record=record)


CASES = {"launcher": launcher_case, "leo": leo_case}


@pytest.fixture(scope="module")
def cases():
    return compiled_cases(CASES)


def make(case, family, compiled=None):
    return Filter(compiled or case["compiled"], family, case["x0"], case["P0"], case["Q"],
                  t0=case["record"][0][0], gate="none")      # the record's start; the references have no gate


def step_all(case, f, steps=None):
    for t, dt, z, q in case["record"][:steps]:
        f.step(t, dt, z, case["measurement"], q=q)


def sigma_error(a, b, P):
    return float(np.max(np.abs(a - b) / np.sqrt(np.diag(P))))


def correlation_error(A, B):
    d = np.sqrt(np.diag(B))
    return float(np.max(np.abs(A - B) / np.outer(d, d)))


@pytest.mark.parametrize("name", CASES)
@pytest.mark.parametrize("square_root, plain", PAIRS)
def test_square_root_equals_plain_filter(cases, name, square_root, plain):
    """Same estimator: x within 1e-6 sigma and P within 1e-6 of its correlation scale (the
    launcher UKF's own reference agrees with it only to ~1e-8 relative: its P - U^T U cancels)."""
    case = cases[name]
    a, b = make(case, square_root), make(case, plain)
    step_all(case, a)
    step_all(case, b)
    tolerance = 1e-6 if plain == "ukf" else 1e-9
    assert sigma_error(a.x, b.x, b.P) < tolerance
    assert correlation_error(a.P, b.P) < tolerance
    assert sigma_error(a.x, case["x0"], b.P) > 0.1          # the updates moved the state (not a trivial pass)


@pytest.mark.parametrize("name", CASES)
@pytest.mark.parametrize("family", ["srukf", "srekf"])
def test_compiled_equals_numpy_reference(cases, name, family):
    """x within 1e-6 sigma, P within 1e-5 of its correlation scale: the launcher's UKF and its own
    NumPy reference differ by 9e-7 of that scale after 9 steps of this record (its P spans 1e-14
    to 1e2), the SR-UKF by 1.5e-6."""
    case = cases[name]
    f = make(case, family)
    ref = SquareRootReference(case["model"], family, case["x0"], case["P0"], case["Q"])
    for t, dt, z, q in case["record"]:
        f.step(t, dt, z, case["measurement"], q=q)
        ref.step(t, dt, z, case["measurement"], q if q is not None else np.zeros(0))
        assert sigma_error(f.x, ref.x, ref.P) < 1e-6
        assert correlation_error(f.P, ref.P) < 1e-5
        np.testing.assert_allclose(f.S(case["measurement"]), ref.S, rtol=1e-6)


@pytest.mark.parametrize("family", ["srukf", "srekf"])
def test_run_equals_steps_and_vm(cases, family):
    case = cases["leo"]
    stepped, whole = make(case, family), make(case, family)
    times = np.array([t + dt for t, dt, _, _ in case["record"]])
    z = np.array([r[2] for r in case["record"]])
    history = [stepped.run(times[:1], z[:1], "tracking").x[0]]       # a run's first step: dt = 0
    for k in range(1, times.size):
        stepped.step(times[k - 1], times[k] - times[k - 1], z[k], "tracking")
        history.append(stepped.x.copy())
    result = whole.run(times, z, "tracking")
    assert not result.failed_steps.size
    np.testing.assert_array_equal(result.x, np.array(history))
    np.testing.assert_array_equal(result.P[-1], stepped.P)
    np.testing.assert_array_equal(whole.factor, stepped.factor)
    vm = make(case, family, load(case["model"], backend="casadi-vm"))
    compiled = make(case, family)
    step_all(case, vm, 6)
    step_all(case, compiled, 6)
    np.testing.assert_allclose(vm.x, compiled.x, rtol=1e-12, atol=1e-9)


@pytest.mark.parametrize("family", ["srukf", "srekf"])
def test_factor_is_lower_triangular_and_carried(cases, family):
    case = cases["launcher"]
    f = make(case, family)
    step_all(case, f, 4)
    Lf = f.factor
    assert np.array_equal(np.triu(Lf, 1), np.zeros_like(Lf))
    assert np.all(np.diag(Lf) > 0)
    np.testing.assert_allclose(Lf @ Lf.T, f.P, rtol=0, atol=1e-15 * np.max(np.abs(f.P)))
    with pytest.raises(ValueError, match="factor"):
        make(case, "ukf").factor


@pytest.mark.parametrize("family", ["srukf", "srekf"])
def test_masks_and_gate(cases, family):
    case = cases["launcher"]
    t, dt, z, q = case["record"][0]
    f, g = make(case, family), make(case, family[2:])
    f.predict(t, dt)
    before = (f.x.copy(), f.factor.copy())
    f.update(z, "radar", q=q, mask=[0, 0, 0])
    assert np.array_equal(f.x, before[0]) and np.array_equal(f.factor, before[1])
    g.predict(t, dt)
    f.update(z, "radar", q=q, mask=[1, 0, 1])
    g.update(z, "radar", q=q, mask=[1, 0, 1])
    assert sigma_error(f.x, g.x, g.P) < 1e-6 and correlation_error(f.P, g.P) < 1e-6
    f.set_gate("radar", threshold=1e-9)
    kept = (f.x.copy(), f.factor.copy())
    assert f.update(z + [500.0, 0, 0], "radar", q=q) == STATUS_GATED
    assert np.array_equal(f.x, kept[0]) and np.array_equal(f.factor, kept[1])


@pytest.mark.parametrize("family", ["srukf", "srekf"])
def test_bad_factor_refused_state_unchanged(cases, family):
    """A factor with a negative diagonal written into the kernel's buffer (as flight code could):
    SYMKF_ERR_NOT_PD, x and the factor unchanged."""
    case = cases["launcher"]
    f = make(case, family)
    f.kernel_buffer("P")[2, 2] = -1e-3
    x, factor = f.x.copy(), f.factor.copy()
    assert f.kernel_call("predict")() == STATUS_NOT_PD
    assert np.array_equal(f.x, x) and np.array_equal(f.factor, factor)


def test_singular_P0_and_negative_kappa(cases):
    """A zero variance (an exactly known state): the UKF's Cholesky of P refuses it, the SR-UKF
    carries a zero column and filters like the UKF started from a variance of 1e-24 there. With
    kappa < 0 (W_0 < 0: the prediction's Cholesky downdate) the SR-UKF still equals the UKF."""
    case = cases["launcher"]
    P0 = case["P0"].copy()
    P0[5, 5] = 0.0
    with pytest.raises(SymkfError, match="NOT_PD"):
        step_all(case, Filter(case["compiled"], "ukf", case["x0"], P0, case["Q"], t0=case["record"][0][0], gate="none"), 1)
    f = Filter(case["compiled"], "srukf", case["x0"], P0, case["Q"], t0=case["record"][0][0], gate="none")
    assert f.factor[5, 5] == 0.0
    step_all(case, f, 3)
    P0[5, 5] = 1e-24
    g = Filter(case["compiled"], "ukf", case["x0"], P0, case["Q"], t0=case["record"][0][0], gate="none")
    step_all(case, g, 3)
    assert sigma_error(f.x, g.x, g.P) < 1e-6
    a, b = (Filter(case["compiled"], family, case["x0"], case["P0"], case["Q"], kappa=-1.0, t0=case["record"][0][0])
            for family in ("srukf", "ukf"))
    for t, dt, _, _ in case["record"][:3]:
        a.predict(t, dt)
        b.predict(t, dt)
    assert sigma_error(a.x, b.x, b.P) < 1e-9 and correlation_error(a.P, b.P) < 1e-9

"""The square-root MEKF (codegen/families/srmekf.py) is the MEKF.

On the star-tracker/gyro attitude model of paper 000 (models/attitude.py: vector-part chart,
exact step, held noise, a quaternion measurement with its own noise) and on the MARG MEKF
(models/marg_mekf.py: series transition, masked heading and gyro-at-rest components), each with
the square-root family beside the MEKF (tests/models/*_square_root_model.py): the square-root MEKF
equals the MEKF in double to round-off, the compiled step equals the NumPy reference
(runtime/reference/square_root_manifold.py), a run equals its steps bit for bit, the carried
factor is lower triangular with L L^T = P, a gated update and a bad factor behave as for every filter.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from symkf.codegen.spec import STATUS_GATED
from symkf.models import attitude as A
from symkf.models import marg_mekf as M
from symkf.runtime import Filter, load
from symkf.runtime.reference import SquareRootManifoldReference
from compiled_cases import compiled_cases

HERE = Path(__file__).resolve().parent.parent / "models"
ATTITUDE = str(HERE / "attitude_square_root_model.py")
MARG = str(HERE / "marg_mekf_square_root_model.py")
MAG = np.array([0.0, 20.0, -40.0])             # the measurement parameter q of the MARG update


def attitude_case():
    q0 = np.array([0.1, -0.2, 0.3, 0.9])
    x0 = np.r_[q0 / np.linalg.norm(q0), 1e-5, -2e-5, 1e-5]
    rng = np.random.default_rng(5)
    record = []
    for k in range(40):
        q_s = x0[:4] + 1e-3 * rng.standard_normal(4)
        record.append(dict(t=0.25 * k, dt=0.25, z=q_s / np.linalg.norm(q_s), u=np.array([1e-3, -2e-3, 5e-4]),
                           q=None, mask=None))
    return dict(model=ATTITUDE, x0=x0, P0=np.diag([1e-4] * 3 + [1e-10] * 3), Q=A.process_noise_psd(),
                R={"star_tracker": A.star_tracker_covariance()}, measurement="star_tracker", record=record,
                attitude=slice(0, 3))


def marg_case():
    rng = np.random.default_rng(6)
    record = []
    for k in range(60):
        acc = np.array([0.05, -0.1, 1.0]) + 0.02 * rng.standard_normal(3)
        mask = np.ones(7)
        mask[3] = 0.0 if k % 5 == 2 else 1.0            # magnetic disturbance: heading unused
        mask[4:] = 0.0 if k % 3 else 1.0                # moving: gyro-at-rest unused
        z = np.r_[acc / np.linalg.norm(acc), 0.02 * rng.standard_normal(), 1e-3 * rng.standard_normal(3)]
        record.append(dict(t=0.01 * k, dt=0.01, z=z, u=np.array([0.01, -0.02, 0.3]) + 1e-3 * rng.standard_normal(3),
                           q=MAG, mask=mask))
    q0 = np.array([0.0, 0.0, np.sin(0.3), np.cos(0.3)])
    return dict(model=MARG, x0=np.r_[q0, 0.002, -0.001, 0.003], P0=np.diag([0.05] * 3 + [1e-4] * 3),
                Q=M.process_noise_psd(), R={}, measurement="marg", record=record, attitude=slice(0, 3))


CASES = {"attitude": attitude_case, "marg": marg_case}


@pytest.fixture(scope="module")
def cases():
    return compiled_cases(CASES)


def make(case, family, compiled=None):
    return Filter(compiled or case["compiled"], family, case["x0"], case["P0"], case["Q"], R=case["R"] or None,
                  t0=case["record"][0]["t"], gate="none")


def step(f, case, r, t="record"):
    return f.step(r["t"] if t == "record" else None, r["dt"], r["z"], case["measurement"], u=r["u"], q=r["q"],
                  mask=r["mask"])


def error_state(case, f, g):
    """The difference f (-) g of two filters' estimates in error coordinates (the attitude by its
    quaternion difference's vector part, doubled: rad to first order)."""
    qf, qg = f.x[:4], g.x[:4]
    dq = np.r_[qg[3] * qf[:3] - qf[3] * qg[:3] - np.cross(qg[:3], qf[:3])]
    return np.r_[2 * dq, f.x[4:] - g.x[4:]]


def sigma_error(case, f, g):
    return float(np.max(np.abs(error_state(case, f, g)) / np.sqrt(np.diag(g.P))))


def correlation_error(A_, B):
    d = np.sqrt(np.diag(B))
    return float(np.max(np.abs(A_ - B) / np.outer(d, d)))


@pytest.mark.parametrize("name", CASES)
def test_square_root_mekf_equals_mekf(cases, name):
    """x within 1e-9 sigma and P within 1e-9 of its correlation scale after every step."""
    case = cases[name]
    a, b = make(case, "srmekf"), make(case, "mekf")
    start = make(case, "mekf")
    for r in case["record"]:
        step(a, case, r)
        step(b, case, r)
        assert sigma_error(case, a, b) < 1e-9
        assert correlation_error(a.P, b.P) < 1e-9
    assert sigma_error(case, b, start) > 0.1           # the updates moved the state (not a trivial pass)
    assert np.max(np.abs(np.diag(a.P) / np.diag(start.P) - 1)) > 0.1


def test_compiled_equals_numpy_reference(cases):
    """On the MARG MEKF (the reference's chart and noise: models/marg_mekf.py), step by step, with masks."""
    case = cases["marg"]
    f = make(case, "srmekf")
    ref = SquareRootManifoldReference(case["model"], "srmekf", case["x0"], case["P0"], case["Q"])
    for r in case["record"]:
        step(f, case, r)
        ref.step(r["t"], r["dt"], r["z"], case["measurement"], r["q"], r["mask"], u=r["u"])
        np.testing.assert_allclose(f.x, ref.x, rtol=0, atol=1e-12)
        assert correlation_error(f.P, ref.P) < 1e-10
        np.testing.assert_allclose(f.S(case["measurement"]), ref.S, rtol=1e-9, atol=1e-15)


@pytest.mark.parametrize("name", CASES)
def test_run_equals_steps_and_vm(cases, name):
    case = cases[name]
    stepped, whole = make(case, "srmekf"), make(case, "srmekf")
    rec = case["record"]
    times = np.array([r["t"] + r["dt"] for r in rec])
    z, u = np.array([r["z"] for r in rec]), np.array([r["u"] for r in rec])
    masks = None if rec[0]["mask"] is None else np.array([r["mask"] for r in rec])
    extra = {} if rec[0]["q"] is None else {"q": rec[0]["q"]}
    history = []
    for r in rec:
        step(stepped, case, r, t="filter")               # the filter's clock, as run_steps
        history.append(stepped.x.copy())
    result = whole.run_steps(np.array([r["dt"] for r in rec]), z, case["measurement"], u=u, mask=masks, **extra)
    assert not result.failed_steps.size
    np.testing.assert_array_equal(result.x, np.array(history))
    np.testing.assert_array_equal(whole.factor, stepped.factor)
    vm = make(case, "srmekf", load(case["model"], backend="casadi-vm"))
    compiled = make(case, "srmekf")
    for r in rec[:8]:
        step(vm, case, r)
        step(compiled, case, r)
    np.testing.assert_allclose(vm.x, compiled.x, rtol=0, atol=1e-13)
    np.testing.assert_allclose(vm.P, compiled.P, rtol=1e-11, atol=1e-20)


def test_factor_is_lower_triangular_and_gate_refuses(cases):
    case = cases["attitude"]
    f = make(case, "srmekf")
    for r in case["record"][:4]:
        step(f, case, r)
    L = f.factor
    assert np.array_equal(np.triu(L, 1), np.zeros_like(L))
    assert np.all(np.diag(L) > 0)
    np.testing.assert_allclose(L @ L.T, f.P, rtol=1e-15, atol=0)
    gated = Filter(case["compiled"], "srmekf", f.x, f.P, case["Q"], R=case["R"], t0=f.t)
    x, P = gated.x.copy(), gated.P.copy()
    r = case["record"][4]
    flipped = np.r_[-r["z"][:3] + 0.2, r["z"][3]]
    code = gated.step(f.t, 0.25, flipped / np.linalg.norm(flipped), case["measurement"], u=r["u"])
    assert code == STATUS_GATED
    assert not np.array_equal(gated.x, x)              # predicted, not updated
    with pytest.raises(ValueError, match="positive semi-definite"):
        Filter(case["compiled"], "srmekf", f.x, -P, case["Q"], R=case["R"], t0=f.t)


def test_copy_is_a_filter_of_its_own(cases):
    case = cases["marg"]
    f = make(case, "srmekf")
    for r in case["record"][:3]:
        step(f, case, r, t="filter")
    clone = f.copy()
    before = (f.x.copy(), f.factor.copy())
    step(clone, case, case["record"][3], t="filter")
    assert np.array_equal(f.x, before[0]) and np.array_equal(f.factor, before[1])
    step(f, case, case["record"][3], t="filter")
    assert np.array_equal(f.x, clone.x) and np.array_equal(f.factor, clone.factor)

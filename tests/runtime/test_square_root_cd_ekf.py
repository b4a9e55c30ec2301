"""The square-root continuous-discrete EKF (codegen/families/srcdekf.py) is the CD-EKF.

On the Koreasat-3 model of paper 003 (models/geo_satellite.py, 17 states, with the square-root
family beside its CD-EKF: tests/models/geo_square_root_model.py), gyro and earth-sensor updates,
some components masked: x equals the CD-EKF's within 1e-9 sigma and P within 2e-8 of its
correlation scale. That difference is the CD-EKF's own: its RK4 of the Riccati ODE over dt = 0.125 s
is 1.2e-8 of that scale from the same filter with 32 sub-steps, the square-root form's
Phi P Phi^T + Q_d 1.1e-13 (measured on this record, NumPy references); the compiled step
equals the NumPy reference (runtime/reference/square_root_cd_ekf.py) to round-off; a run equals
its steps bit for bit; the carried factor is lower triangular.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from symkf.models import geo_satellite as G
from symkf.models import get_model
from symkf.runtime import Filter, load
from symkf.runtime.reference import NumpyCDEKF, NumpySquareRootCDEKF

MODEL = str(Path(__file__).resolve().parent.parent / "models" / "geo_square_root_model.py")
DT = 0.125
U = np.array([0.3, -0.1, 0.2, 0.05])


def record(steps: int = 80):
    """(measurement, z, mask) per step: gyro on three steps of four (one gyro masked on every
    fifth), the earth sensor on the fourth."""
    out = []
    for k in range(1, steps + 1):
        rng = np.random.default_rng(k)
        if k % 4:
            mask = np.ones(4)
            mask[k % 4] = 0.0 if k % 5 == 0 else 1.0
            out.append(("gyro", 1e-4 * rng.standard_normal(4), mask))
        else:
            out.append(("earth_sensor", 1e-3 * rng.standard_normal(2), np.ones(2)))
    return out


@pytest.fixture(scope="module")
def case():
    tune = G.filter_tuning()
    x0 = G.initial_errors(G.TABLE6) + np.r_[np.zeros(3), 1e-3 * np.ones(3), np.zeros(11)]
    return dict(compiled=load(MODEL, backend="compiled"), x0=x0, P0=tune["P0"], Q=tune["Q"], R=tune["R"],
                record=record())


def make(case, family, compiled=None):
    return Filter(compiled or case["compiled"], family, case["x0"], case["P0"], case["Q"], R=case["R"], gate="none")


def step(f, k, entry):
    name, z, mask = entry
    return f.step(None, DT, z, name, u=U, mask=mask)


def scaled_errors(a, b):
    d = np.sqrt(np.diag(b.P))
    return float(np.max(np.abs(a.x - b.x) / d)), float(np.max(np.abs(a.P - b.P) / np.outer(d, d)))


def test_square_root_equals_cd_ekf(case):
    a, b, start = make(case, "srcdekf"), make(case, "cd_ekf"), make(case, "cd_ekf")
    for k, entry in enumerate(case["record"]):
        step(a, k, entry)
        step(b, k, entry)
        x_error, P_error = scaled_errors(a, b)
        assert x_error < 1e-9
        assert P_error < 2e-8
    assert scaled_errors(b, start)[0] > 1.0                # the updates moved the state (not a trivial pass)


def test_time_update_error_is_the_cd_ekfs_rk4():
    """Against the CD-EKF with 32 RK4 sub-steps (converged): the square-root form within 1e-12 of
    the correlation scale, the one-sub-step CD-EKF 1e-9 or more off (its RK4 of the Riccati ODE)."""
    tune = G.filter_tuning()
    x0 = G.initial_errors(G.TABLE6) + np.r_[np.zeros(3), 1e-3 * np.ones(3), np.zeros(11)]
    model = get_model(MODEL)
    made = {"srcdekf": NumpySquareRootCDEKF(model, x0, tune["P0"], tune["Q"], tune["R"]),
            "cd_ekf": NumpyCDEKF(model, x0, tune["P0"], tune["Q"], tune["R"]),
            "converged": NumpyCDEKF(model, x0, tune["P0"], tune["Q"], tune["R"], substeps=32)}
    worst = dict.fromkeys(made, 0.0)
    for k, (name, z, mask) in enumerate(record(40)):
        for f in made.values():
            f.predict(k * DT, DT, u=U)
            f.update(z, measurement=name, mask=mask)
        d = np.sqrt(np.diag(made["converged"].P))
        for family in ("srcdekf", "cd_ekf"):
            worst[family] = max(worst[family], float(np.max(np.abs(made[family].P - made["converged"].P) / np.outer(d, d))))
    assert worst["srcdekf"] < 1e-12
    assert worst["cd_ekf"] > 1e-9


def test_compiled_equals_numpy_reference(case):
    f = make(case, "srcdekf")
    ref = NumpySquareRootCDEKF(get_model(MODEL), case["x0"], case["P0"], case["Q"], case["R"])
    for k, (name, z, mask) in enumerate(case["record"][:24]):
        f.step(None, DT, z, name, u=U, mask=mask)
        ref.predict(k * DT, DT, u=U)
        ref.update(z, measurement=name, mask=mask)
        d = np.sqrt(np.diag(ref.P))
        assert np.max(np.abs(f.x - ref.x) / d) < 1e-11
        assert np.max(np.abs(f.P - ref.P) / np.outer(d, d)) < 1e-11


def test_run_equals_steps_and_vm(case):
    stepped, whole = make(case, "srcdekf"), make(case, "srcdekf")
    gyro = [(z, m) for name, z, m in case["record"] if name == "gyro"][:20]
    history = []
    for z, m in gyro:
        stepped.step(None, DT, z, "gyro", u=U, mask=m)
        history.append(stepped.x.copy())
    result = whole.run_steps(np.full(len(gyro), DT), np.array([z for z, _ in gyro]), "gyro", u=U,
                             mask=np.array([m for _, m in gyro]))
    assert not result.failed_steps.size
    np.testing.assert_array_equal(result.x, np.array(history))
    np.testing.assert_array_equal(whole.factor, stepped.factor)
    vm, compiled = make(case, "srcdekf", load(MODEL, backend="casadi-vm")), make(case, "srcdekf")
    for k, entry in enumerate(case["record"][:6]):
        step(vm, k, entry)
        step(compiled, k, entry)
    np.testing.assert_allclose(vm.x, compiled.x, rtol=1e-12, atol=1e-15)


def test_factor_is_lower_triangular_and_bad_noise_refused(case):
    """The factor is lower triangular with a positive diagonal; a Q that is not PSD is refused, x kept."""
    f = make(case, "srcdekf")
    for k, entry in enumerate(case["record"][:3]):
        step(f, k, entry)
    L = f.factor
    assert np.array_equal(np.triu(L, 1), np.zeros_like(L))
    assert np.all(np.diag(L) > 0)
    x, P = f.x.copy(), f.P.copy()
    with pytest.raises(ValueError, match="Q: not positive semi-definite"):
        f.Q = -case["Q"]
    np.testing.assert_array_equal(f.x, x)
    np.testing.assert_array_equal(f.P, P)


def test_copy_is_a_filter_of_its_own(case):
    f = make(case, "srcdekf")
    for k, entry in enumerate(case["record"][:3]):
        step(f, k, entry)
    clone = f.copy()
    before = (f.x.copy(), f.factor.copy())
    step(clone, 3, case["record"][3])
    assert np.array_equal(f.x, before[0]) and np.array_equal(f.factor, before[1])
    step(f, 3, case["record"][3])
    assert np.array_equal(f.x, clone.x) and np.array_equal(f.factor, clone.factor)

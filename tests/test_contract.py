"""One contract for every model x every filter.

For each generated filter of tests/contract_cases/ (launcher EKF/UKF, geo continuous-discrete
EKF, attitude MEKF/UKF/augmented UKF, four gradient-descent MARG forms, and the manifold MEKF/UKF
of a user model file with a quaternion state, tests/codegen/spinner_model.py):

- compiled == CasADi for every generated function of every bundle;
- compiled == NumPy reference; run == steps (bit for bit); CasADi VM == compiled;
- every class of bad input raises a clear error and leaves x, P and t bit-identical;
- a Hypothesis property over launcher EKF/UKF and MARG steps: either an error with the state
  unchanged, or a finite result with P symmetric positive semi-definite.
"""
from __future__ import annotations

import ctypes
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from contract_cases import Case, all_cases
from contract_cases import marg as marg_cases
from symkf.codegen import generate
from symkf.codegen.spec import STATUS_GATED, STATUS_NONFINITE, STATUS_NOT_PD
from symkf.models import get_model
from symkf.models import launcher as L
from symkf.runtime import Filter, SymkfError, load

N_STEPS = 6
#: Every filter under the contract, one module per model in tests/contract_cases/.
CASES = all_cases()
MODELS = tuple(dict.fromkeys(case.model for case in CASES))


@pytest.fixture(scope="module")
def compiled():
    return {name: load(name, backend="compiled") for name in MODELS}


@pytest.fixture(scope="module")
def vm():
    return {name: load(name, backend="casadi-vm") for name in MODELS}


def tagged(tag: str) -> list[Case]:
    return [case for case in CASES if tag in case.tags]


def step(case: Case, f, k: int, **override):
    """One valid step k (arguments overridden as given)."""
    a = {**case.inputs(k), **override}
    extra = {key: a[key] for key in ("mask", "nan") if key in a}
    return f.step(a["t"], a["dt"], a["z"], measurement=case.measurement, q=a["q"], u=a["u"], **extra)


def run(case: Case, f, n: int, first: int = 1, **override):
    """Steps first .. first + n - 1 as one run (its first step has dt = 0)."""
    rows = [{**case.inputs(k), **override} for k in range(first, first + n)]
    times = run_times(case, n, first)
    z = np.array([r["z"] for r in rows])
    q = None if rows[0]["q"] is None else np.array([r["q"] for r in rows])
    u = None if rows[0]["u"] is None else np.array([r["u"] for r in rows])
    if case.runs_by_steps:
        return f.run_steps(np.array([r["dt"] for r in rows]), z, case.measurement, q=q, u=u)
    return f.run(times, z, measurement=case.measurement, q=q, u=u)


def run_times(case: Case, n: int, first: int = 1) -> np.ndarray:
    rows = [case.inputs(k) for k in range(first, first + n)]
    return np.array([r["t"] + r["dt"] if r["t"] is not None else 0.0 for r in rows])


def snapshot(f):
    return (f.x.copy(), None if "P" not in f._buffers else f.P.copy(), f.t)


def assert_unchanged(f, before):
    x, P, t = before
    assert np.array_equal(f.x, x)
    if P is not None:
        assert np.array_equal(f.P, P)
    assert f.t == t


# ---------------------------------------------------------------------- compiled == CasADi
def _kernel_inputs(kernel, case: Case, rng) -> dict:
    """Valid inputs for any kernel of the case's model (shape-driven, SPD covariances)."""
    a = case.inputs(1)
    values = {}
    for arg in kernel.inputs:
        n, m = arg.shape
        name = arg.name
        if n * m == 0:
            values[name] = np.zeros((n, m))
        elif name == "x" and case.x0.size == n:
            values[name] = case.x0
        elif name in ("P", "Q", "R"):
            B = rng.normal(size=(n, n)) * 0.1
            base = case.P0 if name == "P" and case.P0 is not None and case.P0.shape == (n, n) else np.eye(n)
            d = np.sqrt(np.diag(base))
            values[name] = base + np.diag(d) @ (B @ B.T) @ np.diag(d) * 0.1
        elif name in ("t", "dt"):
            values[name] = np.array([0.05 if name == "dt" else 1.0])
        elif name == "q" and a.get("q") is not None and np.size(a["q"]) == n:   # a second measurement may take other q
            values[name] = a["q"]
        elif name == "z" and np.size(a["z"]) == n:
            values[name] = a["z"]
        elif name == "u" and a.get("u") is not None and np.size(a["u"]) == n:
            values[name] = a["u"]
        elif name == "mask":
            values[name] = np.ones(n)
        elif name == "gate":
            values[name] = np.zeros(n)
        elif name == "kappa":
            values[name] = np.array([1.0])
        elif name == "p":
            values[name] = np.array([v["default"] for v in get_model(case.model).describe()["params"]])
            values[name] = values[name] if values[name].size == n else np.full(n, 0.1)
        elif name in ("quaternions", "q_ref", "q") and n == 4:
            v = rng.normal(size=(4, m if name == "quaternions" else 1))
            values[name] = v / np.linalg.norm(v, axis=0)
        elif name == "weights":
            values[name] = np.full(n, 1.0 / n)
        else:
            values[name] = rng.normal(size=(n, m)) * 0.1
    return values


@pytest.mark.parametrize("model", MODELS, ids=lambda m: Path(m).stem)
def test_every_generated_function_equals_casadi(compiled, model):
    """Every kernel of every bundle, called through its C wrapper, equals CasADi's evaluation."""
    bundle = generate(model)
    case = next(c for c in CASES if c.model == model)
    backend, rng = compiled[model].backend, np.random.default_rng(7)
    for kernel in bundle.kernels:
        inputs = _kernel_inputs(kernel, case, rng)
        expected = kernel.function.call([np.reshape(inputs[a.name], a.shape, order="F") for a in kernel.inputs])
        ins = [np.asfortranarray(np.reshape(inputs[a.name], a.shape, order="F"), dtype=float) for a in kernel.inputs]
        outs = [np.zeros(a.shape, order="F") for a in kernel.outputs[:-1]]
        fn = getattr(backend.lib, f"{compiled[model].name}_{kernel.name}_v")   # the binding entry: one pointer array
        fn.restype, fn.argtypes = ctypes.c_int, [ctypes.c_void_p]
        code = fn((ctypes.c_void_p * (len(ins) + len(outs)))(*[a.ctypes.data for a in ins + outs]))
        status = int(expected[-1])
        assert code == status or (status == 0 and code == STATUS_NONFINITE), kernel.name
        if code not in (0, STATUS_GATED):
            continue
        for arg, got, want in zip(kernel.outputs[:-1], outs, expected[:-1]):
            want = np.asarray(want)
            scale = max(float(np.max(np.abs(want))), 1e-300)
            rel = np.max(np.abs(got - want) / np.maximum(np.abs(want), 1e-3 * scale))
            assert rel <= 1e-11, f"{model}_{kernel.name}.{arg.name}: relative error {rel:.2e}"


# ---------------------------------------------------------------------- three paths agree
@pytest.mark.parametrize("case", CASES, ids=lambda c: c.id)
def test_compiled_equals_numpy_reference(compiled, case):
    """Errors in units of the filter's own standard deviation (absolute for quaternion states)."""
    f = case.make(compiled[case.model])
    states, scales = [], []
    for k in range(1, N_STEPS + 1):
        step(case, f, k)
        states.append(f.x.copy())
        has_P = "P" in f._buffers and f.P.shape[0] == f.x.size
        scales.append(np.sqrt(np.diag(f.P)) if has_P else np.ones(f.x.size))
    reference = np.array(case.reference_states(N_STEPS))
    error = np.max(np.abs(np.array(states) - reference) / np.array(scales))
    assert error < case.tolerance, error


@pytest.mark.parametrize("case", CASES, ids=lambda c: c.id)
def test_run_equals_steps(compiled, case):
    """One run over N steps == a run over its first step (dt = 0) then N - 1 step() calls, bit for bit."""
    whole, stepped = case.make(compiled[case.model]), case.make(compiled[case.model])
    result = run(case, whole, N_STEPS)
    history = [run(case, stepped, 1).x[0]]
    times = run_times(case, N_STEPS)
    for k in range(2, N_STEPS + 1):
        same = {} if case.runs_by_steps else {"t": times[k - 2], "dt": times[k - 1] - times[k - 2]}
        step(case, stepped, k, **same)
        history.append(stepped.x.copy())
    assert not result.failed_steps.size
    np.testing.assert_array_equal(result.x, np.array(history))
    assert_unchanged(whole, snapshot(stepped))


@pytest.mark.parametrize("case", CASES, ids=lambda c: c.id)
def test_vm_equals_compiled(compiled, vm, case):
    a, b = case.make(compiled[case.model]), case.make(vm[case.model])
    for k in range(1, N_STEPS + 1):
        step(case, a, k)
        step(case, b, k)
    np.testing.assert_allclose(b.x, a.x, rtol=1e-12, atol=1e-14)
    runs = run(case, case.make(compiled[case.model]), 3).x, run(case, case.make(vm[case.model]), 3).x
    np.testing.assert_allclose(runs[1], runs[0], rtol=1e-12, atol=1e-14)


# ---------------------------------------------------------------------- bad inputs
def _bad_step_inputs(case: Case) -> dict[str, dict]:
    """Input classes of the issue's matrix that apply to step(), as argument overrides."""
    a = case.inputs(1)
    z = np.asarray(a["z"])
    bad = {"dt negative": {"dt": -a["dt"]}, "dt zero": {"dt": 0.0}, "dt NaN": {"dt": np.nan},
           "dt Inf": {"dt": np.inf}, "dt string": {"dt": "0.05"}, "dt array": {"dt": np.array([0.05, 0.05])},
           "z NaN": {"z": np.where(np.arange(z.size) == 0, np.nan, z)}, "z Inf": {"z": np.where(np.arange(z.size) == 0, np.inf, z)},
           "z short": {"z": z[:-1]}, "z column": {"z": z[:, None]}, "z string": {"z": "abc"},
           "z strings": {"z": [str(v) for v in z]}, "z with a bool": {"z": [True] + [float(v) for v in z[1:]]}, "z complex": {"z": z + 1j}, "z None": {"z": None},
           "u NaN": {"u": np.full(np.size(a["u"]), np.nan)} if a["u"] is not None else None,
           "u shape": {"u": np.zeros(7)}, "nan policy": {"nan": "ignore"},
           "t NaN": {"t": np.nan}, "t string": {"t": "now"},
           "t ahead of the clock": {"t": case.inputs(2)["t"] + 1000.0},
           "t behind the clock": {"t": case.inputs(2)["t"] - 1e6},
           "u forgotten": {"u": None} if a["u"] is not None else None}
    m = case.mask_length()
    bad.update({"mask 0.5": {"mask": np.full(m, 0.5)}, "mask 2": {"mask": np.full(m, 2.0)},
                "mask NaN": {"mask": np.full(m, np.nan)}, "mask shape": {"mask": np.ones(m + 1)}})
    if a["q"] is not None:
        bad.update({"q missing": {"q": None}, "q NaN": {"q": np.full(np.size(a["q"]), np.nan)},
                    "q shape": {"q": np.zeros(np.size(a["q"]) + 1)}})
    return {k: v for k, v in bad.items() if v is not None}


def _bad_settings(case: Case) -> dict[str, tuple[str, object]]:
    """Bad values for settable state (attribute, value)."""
    n = case.x0.size
    bad = {"x NaN": ("x", np.full(n, np.nan)), "x shape": ("x", np.zeros(n + 1)), "x string": ("x", "x")}
    if case.P0 is not None:
        m = case.P0.shape[0]
        asym = np.array(case.P0, dtype=float)
        asym[0, 1] += np.sqrt(asym[0, 0] * asym[1, 1])
        bad.update({"P indefinite": ("P", -case.P0), "P negative variance": ("P", np.diag(np.r_[-1.0, np.ones(m - 1)])),
                    "P asymmetric": ("P", asym), "P NaN": ("P", np.full((m, m), np.nan)),
                    "Q indefinite": ("Q", -np.eye(case.Q.shape[0])), "Q NaN": ("Q", np.full(case.Q.shape, np.nan)),
                    "Q asymmetric": ("Q", np.triu(np.ones(case.Q.shape)) + case.Q.shape[0] * np.eye(case.Q.shape[0]))})
    return bad


@pytest.mark.parametrize("case", CASES, ids=lambda c: c.id)
def test_bad_step_inputs_raise_and_leave_state_bit_identical(compiled, case):
    f = case.make(compiled[case.model])
    step(case, f, 1)
    failures = []
    for label, override in _bad_step_inputs(case).items():
        before = snapshot(f)
        try:
            step(case, f, 2, **override)
            failures.append(f"{label}: accepted")
        except (ValueError, SymkfError):
            pass
        try:
            assert_unchanged(f, before)
        except AssertionError:
            failures.append(f"{label}: state changed")
    assert not failures, failures


@pytest.mark.parametrize("case", CASES, ids=lambda c: c.id)
def test_bad_settings_raise_and_leave_state_bit_identical(compiled, case):
    f = case.make(compiled[case.model])
    step(case, f, 1)
    for label, (attribute, value) in _bad_settings(case).items():
        before = snapshot(f)
        with pytest.raises(ValueError):
            setattr(f, attribute, value)
        assert_unchanged(f, before)


@pytest.mark.parametrize("case", [c for c in CASES if c.P0 is not None], ids=lambda c: c.id)
def test_bad_noise_and_options_are_refused(compiled, case):
    model = compiled[case.model]
    size = case.make(model).R[case.measurement].shape[0]
    R = dict(case.options.get("R", {}))
    for bad_R in (-np.eye(size), np.zeros((size, size)), np.full((size, size), np.nan)):
        with pytest.raises(ValueError, match="R"):
            Filter(model, case.name, case.x0, case.P0, case.Q, **{**case.options, "R": {**R, case.measurement: bad_R}})
    with pytest.raises(ValueError, match="unknown key"):
        Filter(model, case.name, case.x0, case.P0, case.Q, **{**case.options, "R": {**R, case.measurement + "x": np.eye(size)}})
    with pytest.raises(ValueError, match="unknown key"):
        Filter(model, case.name, case.x0, case.P0, case.Q, **{**case.options, "kapa": 1.0})


@pytest.mark.parametrize("case", CASES, ids=lambda c: c.id)
def test_bad_run_inputs_raise_and_leave_state_bit_identical(compiled, case):
    f = case.make(compiled[case.model])
    step(case, f, 1)
    before = snapshot(f)
    a = case.inputs(1)
    times = a["t"] + a["dt"] * np.arange(1, 5)
    z = np.tile(a["z"], (4, 1))
    m = case.mask_length()
    common = dict(measurement=case.measurement, q=a["q"], u=None if a["u"] is None else np.tile(a["u"], (4, 1)))
    bad = [dict(times=times[:, None]), dict(times=times[::-1]), dict(times=np.r_[times[:2], times[1], times[3]]),
           dict(times=np.r_[times[:3], np.nan]), dict(times="abc"), dict(z=np.vstack([z[:1] * np.nan, z[1:]])),
           dict(z=z[:, :-1]), dict(mask=np.full((4, m), 0.5)), dict(mask=np.full((4, m), 2.0)), dict(nan="skip")]
    if a["q"] is not None:
        bad.append(dict(q=None))
    if a["u"] is not None:
        bad.append(dict(u=np.full((4, np.size(a["u"])), np.nan)))
    for override in bad:
        args = {"times": times, "z": z, **common, **override}
        with pytest.raises(ValueError):
            Filter.run(f, args.pop("times"), args.pop("z"), **args)
        assert_unchanged(f, before)


@pytest.mark.parametrize("case", CASES, ids=lambda c: c.id)
def test_nan_mask_policy_skips_the_component(compiled, case):
    """nan="mask" is accepted for every filter and equals skipping that component (or sample)."""
    f, g = case.make(compiled[case.model]), case.make(compiled[case.model])
    a = case.inputs(1)
    z = np.array(a["z"], dtype=float)
    z[0] = np.nan
    mask = np.ones(case.mask_length())
    mask[0] = 0.0                          # that component, or the whole measurement if its mask is one number
    step(case, f, 1, z=z, nan="mask")
    step(case, g, 1, z=np.where(np.isfinite(z), z, 0.0), mask=mask)
    np.testing.assert_array_equal(f.x, g.x)


@pytest.mark.parametrize("case", tagged("separate_update"), ids=lambda c: c.id)
def test_c_refuses_what_python_promises(compiled, case):
    """Past the Python contract (buffers written directly), the C kernels still refuse a P with a
    negative variance (NOT_PD) and report NaN as NONFINITE, writing nothing."""
    f = case.make(compiled[case.model])
    step(case, f, 1)
    a = case.inputs(2)
    f.update(a["z"], measurement=case.measurement, q=a["q"])
    x, P = f.x.copy(), f.P.copy()
    update = f.kernel_call("update", case.measurement)
    buffer = f.kernel_buffer("P")          # P, or a square-root filter's factor L
    kept = buffer[0, 0]
    buffer[0, 0] = -abs(buffer[0, 0])
    assert update() == STATUS_NOT_PD
    buffer[0, 0] = np.nan
    assert update() == STATUS_NONFINITE
    buffer[0, 0] = kept
    assert np.array_equal(f.x, x) and np.array_equal(f.P, P)


@pytest.mark.parametrize("case", tagged("gradient_descent"), ids=lambda c: c.id)
def test_gradient_descent_huge_finite_samples_never_give_a_zero_quaternion(compiled, case):
    """A huge but finite sample is a direction like any other (normalised without overflow)."""
    f, g = case.make(compiled[case.model]), case.make(compiled[case.model])
    a = case.inputs(1)
    step(case, f, 1, z=np.asarray(a["z"]) * np.r_[1e307, 1e307, 1e307, 1e306, 1e306, 1e306][:np.size(a["z"])])
    step(case, g, 1)
    assert abs(np.linalg.norm(f.x) - 1) < 1e-14
    np.testing.assert_allclose(f.x, g.x, atol=1e-14)


# ---------------------------------------------------------------------- gating
@pytest.mark.parametrize("case", tagged("separate_update"), ids=lambda c: c.id)
def test_gate_refuses_an_outlier_and_counts_it(compiled, case):
    gated = case.make(compiled[case.model])
    gated.set_gate(case.measurement, probability=0.999)
    open_ = case.make(compiled[case.model])
    step(case, gated, 1)
    step(case, open_, 1)
    np.testing.assert_array_equal(gated.x, open_.x)            # a normal innovation passes the gate
    a = case.inputs(2)
    outlier = np.array(a["z"]) + 1e3 * np.sqrt(np.diag(gated.R[case.measurement]))
    before = snapshot(gated)
    code = gated.update(outlier, measurement=case.measurement, q=a["q"])
    assert code == STATUS_GATED
    assert_unchanged(gated, before)
    assert gated.y(case.measurement)[0] != 0                    # the diagnostics say why
    times = a["t"] + a["dt"] * np.arange(1, 5)
    z = np.tile(a["z"], (4, 1))
    z[2] = outlier
    result = gated.run(times, z, measurement=case.measurement, q=a["q"],
                       u=None if a["u"] is None else np.tile(a["u"], (4, 1)))
    assert result.gated_steps == 1 and result.status[2] == STATUS_GATED and not result.failed_steps.size


@pytest.mark.parametrize("case", tagged("separate_update"), ids=lambda c: c.id)
def test_a_gated_step_applies_the_prediction_on_both_backends(compiled, vm, case):
    """SYMKF_GATED from step(): the prediction is applied and the update refused, in C and in the
    VM alike (the VM wrote nothing on a gated step: its state stayed at the previous time)."""
    a = case.inputs(2)
    states = []
    for models in (compiled, vm):
        f = case.make(models[case.model])
        f.set_gate(case.measurement, probability=0.999)
        step(case, f, 1)
        before = f.x.copy()
        outlier = np.array(a["z"]) + 1e3 * np.sqrt(np.diag(f.R[case.measurement]))
        assert step(case, f, 2, z=outlier) == STATUS_GATED
        assert not np.array_equal(f.x, before)
        states.append((f.x.copy(), f.P.copy(), f.y(case.measurement).copy()))
    for c_value, vm_value in zip(*states):
        np.testing.assert_allclose(vm_value, c_value, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("case", tagged("quaternion_z"), ids=lambda c: c.id)
def test_attitude_gate_refuses_an_outlier_and_counts_it(compiled, case):
    """Paper 000's filters through the generic gate: a star-tracker quaternion 11° off (σ 0.4 mrad)
    is refused (SYMKF_GATED, the prediction kept), a normal one passes, a run counts the refusal."""
    from scipy.spatial.transform import Rotation
    gated, open_, predicted = (case.make(compiled[case.model]) for _ in range(3))
    gated.set_gate(case.measurement, probability=0.999)
    for f in (gated, open_, predicted):
        step(case, f, 1)
    np.testing.assert_array_equal(gated.x, open_.x)            # a normal innovation passes the gate
    a = case.inputs(2)
    outlier = (Rotation.from_quat(a["z"]) * Rotation.from_rotvec([0.2, 0.0, 0.0])).as_quat()
    assert step(case, gated, 2, z=outlier) == STATUS_GATED
    predicted.predict(a["t"], a["dt"], u=a["u"])
    np.testing.assert_allclose(gated.x, predicted.x, rtol=0, atol=1e-15)   # prediction applied, update refused
    np.testing.assert_allclose(gated.P, predicted.P, rtol=1e-13, atol=0)
    assert np.linalg.norm(gated.y(case.measurement)) > 0.05     # the diagnostics say why (δp ≈ 0.1)
    rows = [case.inputs(k) for k in range(3, 7)]
    near = Rotation.from_quat(gated.x[:4]) * Rotation.from_rotvec(1e-5 * np.random.default_rng(3).normal(size=(4, 3)))
    z = near.as_quat()                                          # consistent with R and the filter's P
    z[2] = (Rotation.from_quat(z[2]) * Rotation.from_rotvec([0.0, -0.2, 0.0])).as_quat()
    result = gated.run_steps(np.array([r["dt"] for r in rows]), z, case.measurement, u=np.array([r["u"] for r in rows]))
    assert result.gated_steps == 1 and result.status[2] == STATUS_GATED and not result.failed_steps.size


def test_gate_settings_are_checked(compiled):
    case = CASES[0]
    f = case.make(compiled[case.model])
    for bad in (dict(probability=1.5), dict(probability=0.0), dict(threshold=-1.0), dict(probability="0.9"),
                dict(probability=0.9, threshold=3.0)):
        with pytest.raises(ValueError):
            f.set_gate("radar", **bad)
    with pytest.raises(ValueError, match="unknown key"):
        Filter(compiled["launcher"], "ekf", case.x0, case.P0, case.Q, gate={"radr": 0.99})


# ---------------------------------------------------------------------- property test
finite = st.floats(min_value=-1e300, max_value=1e300, allow_nan=False)
anything = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.sampled_from([0.0, 1e-300, 1e300, -1.0]))


def _psd(P) -> bool:
    return bool(np.isfinite(P).all() and np.array_equal(P, P.T)
                and np.linalg.eigvalsh(P)[0] >= -1e-8 * max(np.max(np.abs(P)), 1e-300))


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(family=st.sampled_from(["ekf", "ukf"]), dt=anything, z=st.lists(anything, min_size=3, max_size=3),
       mask=st.lists(st.sampled_from([0.0, 1.0]), min_size=3, max_size=3), scale=st.floats(1e-6, 1e6))
def test_property_launcher_step_errs_cleanly_or_stays_psd(compiled, family, dt, z, mask, scale):
    case = CASES[0 if family == "ekf" else 1]
    f = Filter(compiled["launcher"], family, case.x0, case.P0 * scale, case.Q, t0=case.t0, **case.options)
    before = snapshot(f)
    try:
        f.step(f.t, dt, np.array(z), q=L.station_params(2), mask=np.array(mask))
    except (ValueError, SymkfError):
        assert_unchanged(f, before)
        return
    assert np.isfinite(f.x).all() and _psd(f.P)


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(form=st.sampled_from(["simple", "full"]), dt=anything, gyro=st.lists(anything, min_size=3, max_size=3),
       acc=st.lists(anything, min_size=3, max_size=3), mag=st.lists(finite, min_size=3, max_size=3))
def test_property_gradient_descent_step_errs_cleanly_or_stays_unit(compiled, form, dt, gyro, acc, mag):
    case = next(c for c in CASES if c.module is marg_cases and c.name == f"gd_{form}" and c.measurement == "marg")
    f = case.make(compiled["marg"])
    before = snapshot(f)
    try:
        f.step(f.t, dt, np.r_[acc, mag], "marg", u=np.array(gyro))
    except (ValueError, SymkfError):
        assert_unchanged(f, before)
        return
    assert np.isfinite(f.x).all() and abs(np.linalg.norm(f.x) - 1) < 1e-12


@pytest.mark.parametrize("value", [[1000.0, True, 0.2], (1000.0, 0.3, np.bool_(False)), [[1000.0], [False], [0.2]]])
def test_a_bool_inside_a_list_is_refused_not_read_as_one(value):
    """numpy reads [1000.0, True] as [1000.0, 1.0]; the contract refuses it, as it refuses a bool scalar."""
    from symkf.runtime.contract import as_array
    with pytest.raises(ValueError, match="bool"):
        as_array("z", value, (3,) if np.ndim(value) == 1 else (3, 1))
    assert np.array_equal(as_array("z", [1000.0, 1, 0.2], (3,)), [1000.0, 1.0, 0.2])

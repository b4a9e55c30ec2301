"""The MEKF's compiled run iterates ``mekf_run_<m>`` until a step succeeds, then its trusted
partner ``mekf_run_<m>_trusted`` (no test of |q| = 1, P PSD or R diagonal on the loop's own
state: ``mekf.mekf_run_kernels``) or, for the mask patterns of ``manifold_run_variants``
with the gate off, a variant of it with those mask entries constant 0 (as the step function
does with the step's variants). Codes and histories must be exactly those of the checked kernel
called one step at a time, refused steps and refused runs included."""
import numpy as np
import pytest

from kernel_calls import run_in_c, step_by_step
from symkf.codegen.spec import STATUS_ARGS, STATUS_DOMAIN, STATUS_GATED, STATUS_NONFINITE, STATUS_NOT_PD

STEPS = 600
KERNEL = "mekf_run_marg"


@pytest.fixture(scope="module")
def compiled():
    from symkf.runtime import load
    return load("marg_mekf", backend="compiled")


@pytest.fixture(scope="module")
def recording():
    """2.1 s of a synthetic MARG sensor: at rest (the gyro-at-rest rows used), then turning, with
    a magnetic disturbance (the heading masked): every kind of masked component occurs."""
    from symkf.scenarios.marg.data import Recording
    rng = np.random.default_rng(7)
    time = np.arange(STEPS) / 285.714
    gyro = rng.normal(0.0, 2e-3, (STEPS, 3)) + np.where(time[:, None] > 1.6, [0.3, -0.2, 0.8], 0.0)
    acc = rng.normal([0.0, 0.0, 9.81], 0.05, (STEPS, 3))
    mag = rng.normal([0.0, 25.0, -43.0], 0.3, (STEPS, 3))
    mag[440:450] *= 1.2                               # at rest, heading masked
    mag[520:560] *= 1.2                               # turning, heading masked
    return Recording("synthetic", time, gyro, acc, mag)


def inputs(compiled, recording, bad: str) -> dict[str, np.ndarray]:
    """Every input of ``mekf_run_marg`` (per-step ones with one row per step); ``bad`` spoils one."""
    from symkf.models import marg_mekf as marg_ekf
    from symkf.scenarios.marg import mekf as ekf
    filt = ekf.make_filter(compiled, recording)
    mask = ekf.masks(recording)
    patterns = {tuple(np.flatnonzero(row == 0)) for row in mask}
    assert patterns == {(), (3,), (4, 5, 6), (3, 4, 5, 6)}       # every variant of marg_ekf is called
    sigma = [marg_ekf.ACC_DIRECTION_SIGMA] * 3 + [marg_ekf.HEADING_SIGMA] + [marg_ekf.REST_GYRO_SIGMA] * 3
    values = {"t": recording.time - np.r_[0.0, np.diff(recording.time)], "dt": np.r_[3.5e-3, np.diff(recording.time)],
              "x": filt.x.copy(), "P": filt.P.copy(), "u": recording.gyro, "p": np.zeros(0),
              "Q": marg_ekf.process_noise_psd(), "q": recording.mag, "z": ekf.measurements(recording), "mask": mask,
              "R": np.diag(np.square(sigma)), "gate": np.zeros(7)}
    values = {name: np.array(v, dtype=float) for name, v in values.items()}
    if bad == "z":
        values["z"][[0, 1, 300], 0] = np.nan              # the first two steps refused: trusted from step 2
    elif bad == "R":
        values["R"][0, 1] = values["R"][1, 0] = 1e-4      # not diagonal: every step SYMKF_ERR_ARGS
    elif bad == "P":
        values["P"][0, 0] = -1e-3                         # not PSD: every step SYMKF_ERR_NOT_PD
    elif bad == "x":
        values["x"][:4] *= 1.01                           # |q| != 1: every step SYMKF_ERR_DOMAIN
    elif bad == "gate":
        values["gate"][:] = 3.0                           # some steps gated (a success: trusted after)
    return values


@pytest.fixture(scope="module")
def kernels():
    from symkf.codegen import generate
    return {k.name: k for k in generate("marg_mekf").kernels}


def test_the_run_kernel_names_its_trusted_partner_and_its_variants(kernels):
    assert kernels[KERNEL].trusted == f"{KERNEL}_trusted"
    trusted = kernels[f"{KERNEL}_trusted"]
    assert not trusted.runnable and trusted.inputs == kernels[KERNEL].inputs
    assert trusted.function.n_instructions() < kernels[KERNEL].function.n_instructions() - 250
    gate = ("gate", tuple(range(7)))
    expected = [(f"{KERNEL}_masked_3_4_5_6", (gate, ("mask", (3, 4, 5, 6)))),
                (f"{KERNEL}_masked_4_5_6", (gate, ("mask", (4, 5, 6)))), (f"{KERNEL}_masked_3", (gate, ("mask", (3,)))),
                (f"{KERNEL}_ungated", (gate, ("mask", ())))]
    assert list(trusted.variants) == expected
    assert [name for name, _ in kernels["mekf_step_marg"].variants] == \
        [name.replace("mekf_run_", "mekf_step_") for name, _ in expected]
    sizes = [kernels[name].function.n_instructions() for name, _ in expected]
    assert sizes == sorted(sizes) and sizes[-1] < trusted.function.n_instructions()   # masked work is gone


@pytest.mark.parametrize("bad", ["none", "z", "R", "P", "x", "gate"])
def test_run_equals_checked_steps_one_by_one(compiled, recording, bad):
    values = inputs(compiled, recording, bad)
    code, status, x_hist, P_hist = run_in_c(compiled.backend, KERNEL, values, STEPS)
    codes, xs, Ps = step_by_step(compiled.backend, KERNEL, values, STEPS)
    assert status == codes
    assert code == next((c for c in codes if c not in (0, STATUS_GATED)), 0)
    assert np.array_equal(x_hist, xs) and np.array_equal(P_hist, Ps)          # bit for bit
    every = {"R": STATUS_ARGS, "P": STATUS_NOT_PD, "x": STATUS_DOMAIN}
    if bad in every:
        assert set(codes) == {every[bad]} and np.array_equal(x_hist[-1], values["x"])
    else:
        assert codes.count(STATUS_NONFINITE) == (3 if bad == "z" else 0)
        assert not np.array_equal(x_hist[-1], values["x"])                   # the filter moved
    if bad == "gate":
        assert 0 < codes.count(STATUS_GATED) < STEPS


def test_the_trusted_kernel_leaves_out_only_the_tests_of_the_loops_own_state(compiled, recording):
    """Step by step from the same state, the trusted kernel gives the checked kernel's x, P and
    codes bit for bit; given a state the loop never hands it (P not PSD, R not diagonal), it does
    not refuse it."""
    values = inputs(compiled, recording, "none")
    assert all(np.array_equal(a, b) for a, b in zip(step_by_step(compiled.backend, KERNEL, values, STEPS)[1:],
                                                      step_by_step(compiled.backend, f"{KERNEL}_trusted", values, STEPS)[1:]))
    codes, _, _ = step_by_step(compiled.backend, f"{KERNEL}_trusted", inputs(compiled, recording, "R"), STEPS)
    assert STATUS_ARGS not in codes                  # the checked kernel: ARGS at every step
    codes, _, _ = step_by_step(compiled.backend, f"{KERNEL}_trusted", inputs(compiled, recording, "P"), STEPS)
    assert codes[0] == 0                             # the checked kernel: NOT_PD (the update's own pivots may refuse later)


def test_the_step_function_and_its_variants_equal_the_general_step(compiled, recording, kernels):
    """The C step ``mekf_step_marg`` (its wrapper calls a variant for a mask pattern of
    ``manifold_run_variants`` with the gate off) against the general step's CasADi Function
    evaluated in Python, sample by sample on the same inputs: x, P, y, S and codes equal."""
    values = inputs(compiled, recording, "none")
    step = kernels["mekf_step_marg"].function
    backend = compiled.backend
    info = backend.kernels["mekf_step_marg"]
    buffers = {name: np.zeros(shape, order="F") for name, shape in info.inputs + info.outputs[:-1]}
    call = backend.bind("mekf_step_marg", buffers)
    x, P = values["x"], values["P"]
    for k in range(0, STEPS, 7):
        args = {name: (values[name][k] if name in info.per_step else values[name]) for name, _ in info.inputs}
        args["x"], args["P"] = x, P
        args["z"] = np.where(args["mask"] > 0.5, args["z"], 0.0)
        for name, shape in info.inputs:
            if np.prod(shape):
                buffers[name][...] = np.reshape(args[name], shape, order="F")
        code = call()
        expected = step.call({name: args[name] for name, _ in info.inputs})
        assert code == int(expected["status"])
        for name in ("x", "P", "y", "S"):
            assert np.array_equal(buffers[name], np.array(expected[name])), (k, name)
        x, P = buffers["x"][:, 0].copy(), buffers["P"].copy()


def test_a_variant_pattern_outside_the_measurement_is_refused():
    from symkf.codegen import generate
    from symkf.codegen.spec import ConfigError
    from symkf.codegen.generation import default_config
    from symkf.models import get_model
    config = default_config(get_model("marg_mekf")).with_overrides(manifold_run_variants=((7,),))
    with pytest.raises(ConfigError, match="manifold_run_variants"):
        generate("marg_mekf", config)


@pytest.mark.parametrize("mask", [[1, 1, 1, 0, 1, 1, 1], [1, 1, 1, 0, 0, 0, 0], [1] * 7])
def test_a_masked_component_with_a_singular_jacobian_is_ignored_on_both_backends(compiled, mask):
    """A field with no horizontal part (here: none at all) makes the heading's H row infinite.
    Masked, that row must not enter the update, on the C step (which calls a variant with the
    heading folded away) as on the CasADi VM (the general kernel): both accept the step with the
    same x, P. Used, both refuse it (SYMKF_ERR_NOT_PD). Before mekf.masked_rows the VM
    refused the masked case (0 * Inf in H)."""
    from symkf.models import marg_mekf as marg_ekf
    from symkf.runtime import SymkfError, load
    vm = load("marg_mekf", backend="casadi-vm")
    x0, P0 = np.r_[0, 0, 0, 1.0, 0, 0, 0], np.diag([0.01] * 3 + [1e-4] * 3)
    results = []
    for backend in (compiled, vm):
        f = backend.filter("mekf", x0, P0, marg_ekf.process_noise_psd())
        try:
            code = f.step(0.0, 0.01, np.r_[0.1, 0, 0.995, 0, 0, 0, 0], "marg", q=np.zeros(3),
                          mask=np.array(mask, float), u=np.zeros(3))
        except SymkfError as error:
            code = str(error)
        results.append((code, f.x.copy(), f.P.copy()))
    (code_c, x_c, P_c), (code_vm, x_vm, P_vm) = results
    assert np.array_equal(x_c, x_vm) and np.array_equal(P_c, P_vm)
    if mask[3]:
        assert "SYMKF_ERR_NOT_PD" in code_c and "SYMKF_ERR_NOT_PD" in code_vm
    else:
        assert code_c == code_vm == 0 and not np.array_equal(x_c, x0)

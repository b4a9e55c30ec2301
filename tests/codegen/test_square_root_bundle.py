"""The flight-bundle guarantees of the square-root families: srukf and srekf on the LEO model file
(non-additive noise, an angle measurement), srmekf on the attitude model of paper 000 (a quaternion
state and measurement), srcdekf on the geo model of paper 003 (17 states): strict C99 double and
float builds of the exported bundle with only libm, no heap, no mutable globals (the geo bundle's
strict builds take minutes: ``-m slow``; a small continuous-discrete cart model covers srcdekf in
the default run); stack figures
equal to the compiler's; every kernel call of a pass (and the documented edge cases) replayed
under floating-point traps, reproducing Python exactly, an all-masked update leaving x and the
factor bit-identical."""
from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from symkf.codegen import build_model
from symkf.runtime import load

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_flight_bundle import _stated_and_measured_stack  # noqa: E402
from test_trap_safety import (KERNEL_INPUTS, Recorder, assert_harness_reproduces,  # noqa: E402
                              assert_masked_updates_keep_the_state, edge_cases, replay)

MODELS_DIR = Path(__file__).resolve().parent.parent / "models"
LEO = str(MODELS_DIR / "leo_od_model.py")
#: model -> (model file, C prefix, the square-root families, a measurement)
BUNDLES = {"leo": (LEO, "leo_od", ("srukf", "srekf"), "tracking"),
           "attitude": (str(MODELS_DIR / "attitude_square_root_model.py"), "attitude_sr", ("srmekf",), "star_tracker"),
           "cart_cd": (str(MODELS_DIR / "cart_cd_square_root_model.py"), "cart_sr", ("srcdekf",), "range"),
           "geo": (str(MODELS_DIR / "geo_square_root_model.py"), "geo_sr", ("srcdekf",), "gyro")}
#: The bundles as test parameters: the geo model's (17 states: minutes of strict compiles) only with -m slow.
BUNDLE_PARAMS = [pytest.param(name, marks=pytest.mark.slow) if name == "geo" else name for name in BUNDLES]
pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="needs Linux with glibc: the trap tests enable floating-point exceptions with feenableexcept")


@pytest.fixture(scope="module", params=BUNDLE_PARAMS)
def bundle(request, tmp_path_factory):
    path, prefix, families, measurement = BUNDLES[request.param]
    result = build_model(path)
    folder = tmp_path_factory.mktemp(f"{prefix}_flight")
    manifest = json.loads(result.manifest.read_text())
    for name in manifest["sources"] + [f"{prefix}.h", "Makefile"]:
        shutil.copy(result.directory / name, folder / name)
    proc = subprocess.run(["make", "-j2", "-C", str(folder), "all", "float"], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "warning" not in proc.stderr.lower(), proc.stderr[-3000:]
    return folder, prefix, families, measurement


def test_strict_builds_need_only_libm_and_no_heap(bundle):
    folder, prefix, families, measurement = bundle
    for archive in (f"lib{prefix}.a", f"lib{prefix}_float.a"):
        undefined = subprocess.run(["nm", "-u", str(folder / archive)], capture_output=True, text=True).stdout
        assert not re.search(r"\b(malloc|calloc|realloc|free)\b", undefined), undefined
        defined = subprocess.run(["nm", str(folder / archive)], capture_output=True, text=True).stdout
        assert not re.search(r" [BD] ", defined), "mutable global data in the bundle"
        assert {f"{prefix}_{family}_step_{measurement}" for family in families} <= set(re.findall(r" T (\w+)", defined))


def test_stack_figures_are_the_compilers(bundle):
    folder, prefix, families, measurement = bundle
    stated, measured = _stated_and_measured_stack(folder, prefix)
    assert stated == measured
    for family in families:
        assert stated[f"{prefix}_{family}_step_{measurement}_run"] > stated[f"{prefix}_{family}_step_{measurement}"] > 500


def leo_pass(compiled):
    sys.path.insert(0, str(MODELS_DIR))
    import leo_od_model as leo
    case = leo.bench_case(np.random.default_rng(1), n_steps=400)
    for family in ("srukf", "srekf"):
        f = compiled.filter(family, case["x0"], case["P0"], case["Q"])
        f.run(case["times"][:300], case["z"][:300], "tracking", mask=case["mask"][:300])
        for k in range(300, 320):
            f.step(case["times"][k - 1], case["times"][k] - case["times"][k - 1], case["z"][k], "tracking")
        for k in range(320, 340):
            f.predict(case["times"][k - 1], case["times"][k] - case["times"][k - 1])
            f.update(case["z"][k], "tracking")


def attitude_pass(compiled):
    from symkf.models import attitude as A
    rng = np.random.default_rng(2)
    q0 = np.array([0.1, -0.2, 0.3, 0.9])
    x0 = np.r_[q0 / np.linalg.norm(q0), 1e-5, -2e-5, 1e-5]
    f = compiled.filter("srmekf", x0, np.diag([1e-4] * 3 + [1e-10] * 3), A.process_noise_psd(),
                        R={"star_tracker": A.star_tracker_covariance()}, gate="none")
    z = x0[:4] + 1e-4 * rng.standard_normal((700, 4))
    z /= np.linalg.norm(z, axis=1)[:, None]
    f.run_steps(np.full(600, 0.25), z[:600], "star_tracker", u=np.array([1e-3, -2e-3, 5e-4]))
    for k in range(600, 700):
        f.predict(None, 0.25, u=np.array([1e-3, -2e-3, 5e-4]))
        f.update(z[k], "star_tracker")


def geo_pass(compiled):
    from symkf.models import geo_satellite as G
    tune = G.filter_tuning()
    x0 = G.initial_errors(G.TABLE6)
    f = compiled.filter("srcdekf", x0, tune["P0"], tune["Q"], R=tune["R"], gate="none")
    rng = np.random.default_rng(3)
    u = np.array([0.3, -0.1, 0.2, 0.05])
    f.run_steps(np.full(600, 0.125), 1e-4 * rng.standard_normal((600, 4)), "gyro", u=u)
    for k in range(100):
        f.predict(None, 0.125, u=u)
        f.update(1e-3 * rng.standard_normal(2), "earth_sensor")


def cart_cd_pass(compiled):
    f = compiled.filter("srcdekf", np.array([0.0, 1.0]), np.diag([1.0, 0.25]), np.diag([1e-6, 0.01]), gate="none")
    rng = np.random.default_rng(3)
    u = np.array([0.5])
    f.run_steps(np.full(600, 0.1), 1.0 + 0.05 * rng.standard_normal((600, 1)), "tacho", u=u)
    for k in range(100):
        f.predict(None, 0.1, u=u)
        f.update([np.hypot(f.x[0], 3.0) + 0.1 * rng.standard_normal()], "range")


PASSES = {"leo": leo_pass, "attitude": attitude_pass, "cart_cd": cart_cd_pass, "geo": geo_pass}


@pytest.mark.parametrize("model", BUNDLE_PARAMS)
def test_square_root_kernels_do_not_trap(model, monkeypatch, tmp_path):
    compiled = load(BUNDLES[model][0], backend="compiled")
    recorder = Recorder(monkeypatch)
    PASSES[model](compiled)
    monkeypatch.undo()
    kernels = compiled.backend.kernels
    KERNEL_INPUTS.update({name: [n for n, _ in k.inputs] for name, k in kernels.items()})
    nominal = [c for c in recorder.calls if c[0].startswith("sr")]
    assert len(nominal) > 600
    extra = edge_cases(nominal)
    statuses, _, outputs = replay(tmp_path, compiled, nominal + extra)
    assert_harness_reproduces(nominal, statuses, outputs)
    masked = assert_masked_updates_keep_the_state(nominal, extra, statuses, outputs)
    for (kernel, _, _, label), status in zip(extra, statuses[len(nominal):]):
        if label == "P=-1.0":
            assert status == 2, kernel                     # a negative diagonal of the factor: NOT_PD
    assert masked

"""The flight-bundle guarantees of the square-root families (srukf, srekf) on the LEO model file
(non-additive noise, an angle measurement): strict C99 double and float builds of the exported
bundle with only libm, no heap, no mutable globals; stack figures equal to the compiler's; every
kernel call of a pass (and the documented edge cases) replayed under floating-point traps,
reproducing Python exactly, an all-masked update leaving x and the factor bit-identical."""
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

LEO = str(Path(__file__).resolve().parent.parent / "models" / "leo_od_model.py")
pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="needs Linux with glibc: the trap tests enable floating-point exceptions with feenableexcept")


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    result = build_model(LEO)
    folder = tmp_path_factory.mktemp("leo_flight")
    manifest = json.loads(result.manifest.read_text())
    for name in manifest["sources"] + ["leo_od.h", "Makefile"]:
        shutil.copy(result.directory / name, folder / name)
    proc = subprocess.run(["make", "-j2", "-C", str(folder), "all", "float"], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "warning" not in proc.stderr.lower(), proc.stderr[-3000:]
    return folder, manifest


def test_strict_builds_need_only_libm_and_no_heap(bundle):
    folder, _ = bundle
    for archive in ("libleo_od.a", "libleo_od_float.a"):
        undefined = subprocess.run(["nm", "-u", str(folder / archive)], capture_output=True, text=True).stdout
        assert not re.search(r"\b(malloc|calloc|realloc|free)\b", undefined), undefined
        defined = subprocess.run(["nm", str(folder / archive)], capture_output=True, text=True).stdout
        assert not re.search(r" [BD] ", defined), "mutable global data in the bundle"
        assert {"leo_od_srukf_step_tracking", "leo_od_srekf_step_tracking"} <= set(re.findall(r" T (\w+)", defined))


def test_stack_figures_are_the_compilers(bundle):
    folder, _ = bundle
    stated, measured = _stated_and_measured_stack(folder, "leo_od")
    assert stated == measured
    assert stated["leo_od_srukf_step_tracking_run"] > stated["leo_od_srukf_step_tracking"] > 1000


def test_square_root_kernels_do_not_trap(monkeypatch, tmp_path):
    sys.path.insert(0, str(Path(LEO).parent))
    import leo_od_model as leo
    compiled = load(LEO, backend="compiled")
    case = leo.bench_case(np.random.default_rng(1), n_steps=400)
    recorder = Recorder(monkeypatch)
    for family in ("srukf", "srekf"):
        f = compiled.filter(family, case["x0"], case["P0"], case["Q"])
        f.run(case["times"][:300], case["z"][:300], "tracking", mask=case["mask"][:300])
        for k in range(300, 320):
            f.step(case["times"][k - 1], case["times"][k] - case["times"][k - 1], case["z"][k], "tracking")
        for k in range(320, 340):
            f.predict(case["times"][k - 1], case["times"][k] - case["times"][k - 1])
            f.update(case["z"][k], "tracking")
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

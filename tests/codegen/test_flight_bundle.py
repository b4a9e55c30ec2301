"""The flight bundle: strict standalone builds (double and float), no heap, a C harness that
reproduces the Python filter, and a header that documents every function."""
import json
import re
import shutil
import subprocess

import numpy as np
import pytest

from symkf.codegen import build_model
from symkf.models import launcher as L
from symkf.scenarios.launcher.truth import propagate, radar_track

HARNESS = r"""
#include <stdio.h>
#include "launcher.h"
/* stdin: x0[6] P0[36] Q[36] R[9] kappa p[6] n, then n lines: t dt q[2] z[3] mask[3]; stdout: x per step */
static int read(double *v, int n) { int i; for (i = 0; i < n; ++i) if (scanf("%lf", &v[i]) != 1) return 0; return 1; }
int main(int argc, char **argv) {
  double x[6], P[36], Q[36], R[9], kappa, p[6], t, dt, q[2], z[3], mask[3], y[3], S[9], u[1], gate[3] = {0, 0, 0};
  int n, k, i, code, ukf = argc > 1;
  (void)argv;
  if (!read(x, 6) || !read(P, 36) || !read(Q, 36) || !read(R, 9) || !read(&kappa, 1) || !read(p, 6)) return 2;
  if (scanf("%d", &n) != 1) return 2;
  for (k = 0; k < n; ++k) {
    if (!read(&t, 1) || !read(&dt, 1) || !read(q, 2) || !read(z, 3) || !read(mask, 3)) return 2;
    code = ukf ? launcher_ukf_step_radar(&t, &dt, x, P, u, p, Q, q, z, mask, R, gate, &kappa, x, P, y, S)
               : launcher_ekf_step_radar(&t, &dt, x, P, u, p, Q, q, z, mask, R, gate, x, P, y, S);
    if (code) { printf("error %d\n", code); return 1; }
    for (i = 0; i < 6; ++i) printf("%.17g ", x[i]);
    printf("\n");
  }
  return 0;
}
"""


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    """build/launcher/ copied alone (no CasADi, no Python) and built with its own Makefile."""
    result = build_model("launcher")
    folder = tmp_path_factory.mktemp("flight")
    for name in ("launcher.c", "launcher.h", "Makefile"):
        shutil.copy(result.directory / name, folder / name)
    proc = subprocess.run(["make", "-j2", "-C", str(folder), "all", "float"], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "warning" not in proc.stderr.lower()
    return folder, json.loads(result.manifest.read_text())


@pytest.fixture(scope="module")
def harness(bundle):
    folder, _ = bundle
    (folder / "harness.c").write_text(HARNESS)
    exe = folder / "harness"
    proc = subprocess.run(["cc", "-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-O2", "-o", str(exe),
                           str(folder / "harness.c"), str(folder / "liblauncher.a"), "-lm"],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return exe


def test_strict_double_and_float_builds_need_only_libm(bundle):
    folder, _ = bundle
    for archive in ("liblauncher.a", "liblauncher_float.a"):
        undefined = subprocess.run(["nm", "-u", str(folder / archive)], capture_output=True, text=True).stdout
        assert not re.search(r"\b(malloc|calloc|realloc|free)\b", undefined), undefined
        external = set(re.findall(r"U (\w+)", undefined))
        assert external <= {"sin", "cos", "sincos", "exp", "atan2", "sqrt", "fmin", "fmax", "ceil", "memset", "memcpy",
                            "sinf", "cosf", "sincosf", "expf", "atan2f", "sqrtf", "fminf", "fmaxf", "ceilf"}, external
        defined = subprocess.run(["nm", str(folder / archive)], capture_output=True, text=True).stdout
        assert not re.search(r" [BD] ", defined), "mutable global data in the bundle"


def test_header_documents_every_function(bundle):
    folder, manifest = bundle
    header = (folder / "launcher.h").read_text()
    for kernel in manifest["kernels"]:
        assert f"int launcher_{kernel['name']}(" in header
        assert f"LAUNCHER_{kernel['name'].upper()}_WORK_BYTES" in header
        for arg in kernel["inputs"]:
            assert re.search(rf"in  {re.escape(arg['name'])}\s+\[{arg['shape'][0]}x{arg['shape'][1]}\] \(", header)
    for code in ("SYMKF_OK", "SYMKF_ERR_NOT_PD", "SYMKF_ERR_NONFINITE"):
        assert code in header


@pytest.mark.parametrize("family", ["ekf", "ukf"])
def test_c_harness_reproduces_python(harness, launcher_compiled, family):
    exe = harness
    times = np.arange(41) * 0.05
    truth = propagate(times)
    track = radar_track(times, truth)
    z, q = track.noisy(np.random.default_rng(3)), track.station_params()
    mask = np.ones_like(z)
    mask[5, 2] = 0.0
    x0, P0 = truth[0] + [5.0, 0, 0, 500.0, 0, 0], np.diag([10.0, 1e-4, 1e-4, 1e3, 1e-5, 1e-5]) ** 2
    Q, R, kappa, p = np.diag([1.0, 1e-8, 1e-8, 1.0, 1e-14, 1e-14]), np.diag(np.square(L.RADAR_SIGMA)), 1.0, \
        [v for k, v in L.GUIDANCE.items() if k in L.GUIDANCE_PARAMS]
    def numbers(values):
        return " ".join(f"{v:.17g}" for v in values)

    lines = [numbers(np.concatenate([x0, P0.ravel("F"), Q.ravel("F"), R.ravel("F"), [kappa], p])),
             str(len(times) - 1)]
    lines += [numbers(np.concatenate([[times[k - 1], 0.05], q[k], z[k], mask[k]]))
              for k in range(1, len(times))]
    out = subprocess.run([str(exe)] + (["ukf"] if family == "ukf" else []), input="\n".join(lines),
                         capture_output=True, text=True).stdout
    assert "error" not in out, out[-300:]
    c_states = np.array([[float(v) for v in line.split()] for line in out.strip().splitlines()])
    f = launcher_compiled.filter(family, x0, P0, Q, **({"kappa": kappa} if family == "ukf" else {}))
    for k in range(1, len(times)):
        f.step(times[k - 1], 0.05, z[k], q=q[k], mask=mask[k])
        np.testing.assert_allclose(c_states[k - 1], f.x, rtol=1e-13, atol=0)

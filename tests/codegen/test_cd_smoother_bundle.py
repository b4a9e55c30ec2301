"""The continuous-discrete EKF smoother in the flight bundle: a strict standalone build (double
and float, no heap), and a C program that runs the forward loop and the backward loop on its own
stack arrays and reproduces the Python smoothing (masked steps included)."""
import json
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from symkf.codegen import build_model
from symkf.runtime import load

MODEL = str(Path(__file__).parents[1] / "runtime" / "cd_linear_model.py")

HARNESS = r"""
#include <stdio.h>
#include "cd_linear.h"
#define MAX_STEPS 200
/* stdin: n, then n lines: dt z mask; stdout: the smoothed x and the diagonal of Ps per step, then the codes */
int main(void) {
  static const casadi_real x0[3] = {1.0, 0.0, 0.5}, P0[9] = {1, 0, 0, 0, 1, 0, 0, 0, 0.5};
  static const casadi_real Q[9] = {1e-4, 0, 0, 0, 1e-2, 0, 0, 0, 1e-3};
  casadi_real t[MAX_STEPS], dt[MAX_STEPS], z[MAX_STEPS], mask[MAX_STEPS];
  casadi_real x_hist[MAX_STEPS * 3], P_hist[MAX_STEPS * 9], xs_hist[MAX_STEPS * 3], Ps_hist[MAX_STEPS * 9];
  int status[MAX_STEPS], smooth_status[MAX_STEPS], n, k, i, forward, backward;
  if (scanf("%d", &n) != 1 || n > MAX_STEPS) return 2;
  for (k = 0; k < n; ++k) {
    if (scanf("%lf %lf %lf", &dt[k], &z[k], &mask[k]) != 3) return 2;
    t[k] = k ? t[k - 1] + dt[k - 1] : 0.0;
  }
  forward = cd_linear_cd_ekf_step_position_run(n, t, dt, x0, P0, Q, z, mask, 0.09, 0.0, x_hist, P_hist, status);
  backward = cd_linear_cd_ekf_smooth_run(n, t, dt, x_hist, P_hist, Q, status, xs_hist, Ps_hist, smooth_status);
  for (k = 0; k < n; ++k) {
    for (i = 0; i < 3; ++i) printf("%.17g ", xs_hist[k * 3 + i]);
    for (i = 0; i < 3; ++i) printf("%.17g ", Ps_hist[k * 9 + 4 * i]);
    printf("\n");
  }
  printf("codes %d %d\n", forward, backward);
  return 0;
}
"""


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    result = build_model(MODEL)
    folder = tmp_path_factory.mktemp("cd_smoother_flight")
    manifest = json.loads(result.manifest.read_text())
    for name in manifest["sources"] + ["cd_linear.h", "Makefile"]:
        shutil.copy(result.directory / name, folder / name)
    proc = subprocess.run(["make", "-j2", "-C", str(folder), "all", "float"], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "warning" not in proc.stderr.lower()
    return folder, manifest


def test_manifest_and_strict_builds_need_no_heap(bundle):
    folder, manifest = bundle
    assert {f["name"]: f for f in manifest["filters"]}["cd_ekf"]["smooth"] == "cd_ekf_smooth"
    kernel = {k["name"]: k for k in manifest["kernels"]}["cd_ekf_smooth"]
    assert kernel["backward"] == ["xs", "Ps"] and kernel["carried"] == []
    header = (folder / "cd_linear.h").read_text()
    assert re.search(r"#define CD_LINEAR_CD_EKF_SMOOTH_RUN_STACK_BYTES [1-9]\d*", header)
    for archive in ("libcd_linear.a", "libcd_linear_float.a"):
        undefined = subprocess.run(["nm", "-u", str(folder / archive)], capture_output=True, text=True).stdout
        assert not re.search(r"\b(malloc|calloc|realloc|free)\b", undefined), undefined
        defined = subprocess.run(["nm", str(folder / archive)], capture_output=True, text=True).stdout
        assert re.search(r" T cd_linear_cd_ekf_smooth_run\b", defined)
        assert not re.search(r" [BD] ", defined), "mutable global data in the bundle"


def test_c_program_smooths_as_python_does(bundle):
    folder, _ = bundle
    (folder / "harness.c").write_text(HARNESS)
    exe = folder / "harness"
    proc = subprocess.run(["cc", "-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-O2", "-o", str(exe),
                           str(folder / "harness.c"), str(folder / "libcd_linear.a"), "-lm"],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    rng = np.random.default_rng(4)
    n = 150
    dt = np.full(n, 0.1)
    z = np.sin(0.8 * np.cumsum(dt)) + rng.normal(0.0, 0.3, n)
    mask = np.ones(n)
    mask[50:70] = 0.0
    text = f"{n}\n" + "".join(f"{float(a)!r} {float(b)!r} {float(c)!r}\n" for a, b, c in zip(dt, z, mask))
    out = subprocess.run([str(exe)], input=text, capture_output=True, text=True, check=True).stdout.splitlines()
    assert out[-1] == "codes 0 0"
    c_out = np.array([[float(v) for v in line.split()] for line in out[:-1]])
    f = load(MODEL).filter("cd_ekf", [1.0, 0.0, 0.5], np.diag([1.0, 1.0, 0.5]), np.diag([1e-4, 1e-2, 1e-3]),
                           R={"position": np.array([[0.09]])})
    run = f.run_steps(dt, z[:, None], "position", mask=mask[:, None], smooth=True)
    np.testing.assert_allclose(c_out[:, :3], run.x_smooth, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(c_out[:, 3:], np.einsum("kii->ki", run.P_smooth), rtol=1e-12, atol=1e-14)
    assert not np.allclose(run.x_smooth[:-1], run.x[:-1])      # smoothing moved the estimate

"""The smoothers in the flight bundle: strict standalone builds (double and float, no heap), and C
programs that run the forward loop and the backward loop on their own arrays and reproduce the
Python smoothing: the EKF's RTS (radar model) and the continuous-discrete EKF's (an oscillator,
masked steps included)."""
import json
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from symkf.codegen import build_model
from symkf.runtime import load

MODEL = str(Path(__file__).parents[1] / "runtime" / "rts_radar_model.py")
CD_MODEL = str(Path(__file__).parents[1] / "runtime" / "cd_linear_model.py")

HARNESS = r"""
#include <stdio.h>
#include "rts_radar.h"
#define MAX_STEPS 200
/* stdin: n, then n lines: dt z u; stdout: the smoothed x per step, then the first error codes */
int main(void) {
  static const casadi_real x0[3] = {0.0, 90.0, 1100.0}, P0[9] = {100, 0, 0, 0, 100, 0, 0, 0, 100};
  static const casadi_real Q[9] = {0.1, 0, 0, 0, 0.1, 0, 0, 0, 0.1};
  casadi_real t[MAX_STEPS], dt[MAX_STEPS], z[MAX_STEPS], u[MAX_STEPS], mask[MAX_STEPS];
  casadi_real x_hist[MAX_STEPS * 3], P_hist[MAX_STEPS * 9], xs_hist[MAX_STEPS * 3], Ps_hist[MAX_STEPS * 9];
  int status[MAX_STEPS], smooth_status[MAX_STEPS], n, k, i, forward, backward;
  if (scanf("%d", &n) != 1 || n > MAX_STEPS) return 2;
  for (k = 0; k < n; ++k) {
    if (scanf("%lf %lf %lf", &dt[k], &z[k], &u[k]) != 3) return 2;
    t[k] = k ? t[k - 1] + dt[k - 1] : 0.0;
    mask[k] = 1.0;
  }
  forward = rts_radar_ekf_step_range_run(n, t, dt, x0, P0, u, Q, z, mask, 10.0, 0.0, x_hist, P_hist, status);
  backward = rts_radar_ekf_smooth_run(n, t, dt, x_hist, P_hist, u, Q, status, xs_hist, Ps_hist, smooth_status);
  for (k = 0; k < n; ++k) {
    for (i = 0; i < 3; ++i) printf("%.17g ", xs_hist[k * 3 + i]);
    printf("\n");
  }
  printf("codes %d %d\n", forward, backward);
  return 0;
}
"""


def flight_folder(model: str, folder: Path):
    """The model's bundle copied alone into ``folder`` and built with its own Makefile (double and float)."""
    result = build_model(model)
    manifest = json.loads(result.manifest.read_text())
    for name in manifest["sources"] + [f"{manifest['model']}.h", "Makefile"]:
        shutil.copy(result.directory / name, folder / name)
    proc = subprocess.run(["make", "-j2", "-C", str(folder), "all", "float"], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "warning" not in proc.stderr.lower()
    return folder, manifest


def harness_output(folder: Path, source: str, library: str, stdin: str) -> list[str]:
    """The lines a C program ``source`` prints, compiled strictly against the bundle's ``library``."""
    (folder / "harness.c").write_text(source)
    exe = folder / "harness"
    proc = subprocess.run(["cc", "-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-O2", "-o", str(exe),
                           str(folder / "harness.c"), str(folder / library), "-lm"], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return subprocess.run([str(exe)], input=stdin, capture_output=True, text=True, check=True).stdout.splitlines()

CD_HARNESS = r"""
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
    return flight_folder(MODEL, tmp_path_factory.mktemp("smoother_flight"))


@pytest.fixture(scope="module")
def cd_bundle(tmp_path_factory):
    return flight_folder(CD_MODEL, tmp_path_factory.mktemp("cd_smoother_flight"))


def test_manifest_names_the_smoother_of_each_filter(bundle):
    _, manifest = bundle
    filters = {f["name"]: f for f in manifest["filters"]}
    assert filters["ekf"]["smooth"] == "ekf_smooth" and filters["ukf"]["smooth"] == "ukf_smooth"
    kernels = {k["name"]: k for k in manifest["kernels"]}
    assert kernels["ekf_smooth"]["backward"] == ["xs", "Ps"]
    assert kernels["ekf_smooth"]["carried"] == []           # no forward run loop for it


def test_c_program_smooths_as_python_does(bundle):
    folder, _ = bundle
    rng = np.random.default_rng(4)
    n = 150
    dt = np.full(n, 0.1)
    u = rng.normal(0.0, 1.0, n)
    pos = np.cumsum(90.0 * dt + np.cumsum(u * dt) * dt)
    z = np.hypot(pos, 1100.0) + rng.normal(0.0, 3.0, n)
    text = f"{n}\n" + "".join(f"{float(a)!r} {float(b)!r} {float(c)!r}\n" for a, b, c in zip(dt, z, u))
    out = harness_output(folder, HARNESS, "librts_radar.a", text)
    assert out[-1] == "codes 0 0"
    c_smoothed = np.array([[float(v) for v in line.split()] for line in out[:-1]])
    f = load(MODEL).ekf([0.0, 90.0, 1100.0], np.eye(3) * 100.0, np.eye(3) * 0.1, R={"range": np.array([[10.0]])})
    run = f.run_steps(dt, z[:, None], "range", u=u[:, None], smooth=True)
    np.testing.assert_allclose(c_smoothed, run.x_smooth, rtol=1e-12, atol=1e-9)
    assert not np.allclose(run.x_smooth[:-1], run.x[:-1])      # smoothing moved the estimate


def test_cd_smoother_builds_strictly_without_heap(cd_bundle):
    folder, manifest = cd_bundle
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


def test_c_program_smooths_the_cd_ekf_as_python_does(cd_bundle):
    folder, _ = cd_bundle
    rng = np.random.default_rng(4)
    n = 150
    dt = np.full(n, 0.1)
    z = np.sin(0.8 * np.cumsum(dt)) + rng.normal(0.0, 0.3, n)
    mask = np.ones(n)
    mask[50:70] = 0.0
    text = f"{n}\n" + "".join(f"{float(a)!r} {float(b)!r} {float(c)!r}\n" for a, b, c in zip(dt, z, mask))
    out = harness_output(folder, CD_HARNESS, "libcd_linear.a", text)
    assert out[-1] == "codes 0 0"
    c_out = np.array([[float(v) for v in line.split()] for line in out[:-1]])
    f = load(CD_MODEL).filter("cd_ekf", [1.0, 0.0, 0.5], np.diag([1.0, 1.0, 0.5]), np.diag([1e-4, 1e-2, 1e-3]),
                              R={"position": np.array([[0.09]])})
    run = f.run_steps(dt, z[:, None], "position", mask=mask[:, None], smooth=True)
    np.testing.assert_allclose(c_out[:, :3], run.x_smooth, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(c_out[:, 3:], np.einsum("kii->ki", run.P_smooth), rtol=1e-12, atol=1e-14)
    assert not np.allclose(run.x_smooth[:-1], run.x[:-1])      # smoothing moved the estimate

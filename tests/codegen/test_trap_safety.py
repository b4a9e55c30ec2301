"""Trap-safe kernels: every kernel call of a nominal flight of each of the four models, plus the
documented edge cases (all-masked updates, a zero MARG sample), replayed in a C harness that runs
with ``feenableexcept(FE_DIVBYZERO | FE_INVALID | FE_OVERFLOW)``: any division by zero, invalid
operation or overflow -- even in a branch the kernel then discards -- kills the harness with SIGFPE.

The calls are recorded from the Python filters (``CompiledBackend.bind`` and ``run_function``
wrapped while a scenario runs); ``_run`` calls are expanded into their per-step calls. The
harness calls each kernel's ``<model>_<kernel>_v`` entry and writes status and outputs back, which
must equal what the Python side got (same code, so exactly).
"""
from __future__ import annotations

import ctypes
import subprocess
import sys

import numpy as np
import pytest

from symkf.runtime import load
from symkf.runtime.backends import BoundCall, CompiledBackend

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="needs Linux with glibc: the trap tests enable floating-point exceptions with feenableexcept")

HARNESS = r"""
#define _GNU_SOURCE
#include <fenv.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>
#include "{model}.h"
/* stdin-free: argv[1] = records (doubles: kernel index, then every input), argv[2] = results
   (per record: status, then every output). FP traps on for the whole run. */
typedef int (*entry_t)(casadi_real *const *);
static const entry_t entries[] = {{{entries}}};
static const int n_in[] = {{{n_in}}};
static const int n_out[] = {{{n_out}}};
static const int sizes[][{max_args}] = {{{sizes}}};
static volatile long current = -1;
static volatile int current_kernel = -1;
static void on_trap(int sig, siginfo_t *info, void *context) {{
  char text[160];
  int n = snprintf(text, sizeof text, "SIGFPE (%s) in record %ld, kernel index %d\n",
                   info->si_code == FPE_FLTDIV ? "division by zero" : info->si_code == FPE_FLTINV ? "invalid"
                   : info->si_code == FPE_FLTOVF ? "overflow" : "other", current, current_kernel);
  (void)sig; (void)context;
  if (n > 0) (void)!write(2, text, (size_t) n);
  _exit(9);
}}
int main(int argc, char **argv) {{
  static double buffer[{max_total}];
  casadi_real *pointers[{max_args}];
  double kernel, code;
  long calls = 0;
  int a, offset, inputs, outputs;
  FILE *in, *out;
  if (argc < 3 || !(in = fopen(argv[1], "rb")) || !(out = fopen(argv[2], "wb"))) return 2;
  struct sigaction action;
  memset(&action, 0, sizeof action);
  action.sa_sigaction = on_trap;
  action.sa_flags = SA_SIGINFO;
  sigaction(SIGFPE, &action, NULL);
  int trap = argc < 4;                /* argv[3] given: record the raised flags instead of trapping */
  double flags;
  if (trap) feenableexcept(FE_DIVBYZERO | FE_INVALID | FE_OVERFLOW);
  while (fread(&kernel, sizeof kernel, 1, in) == 1) {{
    int k = (int) kernel;
    for (a = 0, offset = 0; a < n_in[k] + n_out[k]; ++a) {{
      pointers[a] = buffer + offset;
      offset += sizes[k][a] > 0 ? sizes[k][a] : 1;
    }}
    for (a = 0, inputs = 0; a < n_in[k]; ++a) inputs += sizes[k][a];
    for (outputs = 0; a < n_in[k] + n_out[k]; ++a) outputs += sizes[k][a];
    for (a = 0; a < n_in[k]; ++a)
      if (sizes[k][a] && fread(pointers[a], sizeof(double), (size_t) sizes[k][a], in) != (size_t) sizes[k][a]) return 3;
    for (; a < n_in[k] + n_out[k]; ++a) memset(pointers[a], 0, sizeof(double) * (size_t) (sizes[k][a] ? sizes[k][a] : 1));
    current = calls;
    current_kernel = k;
    feclearexcept(FE_ALL_EXCEPT);
    code = entries[k](pointers);
    flags = (double) fetestexcept(FE_DIVBYZERO | FE_INVALID | FE_OVERFLOW);
    fwrite(&code, sizeof code, 1, out);
    fwrite(&flags, sizeof flags, 1, out);
    for (a = n_in[k]; a < n_in[k] + n_out[k]; ++a) fwrite(pointers[a], sizeof(double), (size_t) sizes[k][a], out);
    ++calls;
  }}
  (void)inputs; (void)outputs;
  fclose(out);
  printf("%ld calls\n", calls);
  return 0;
}}
"""


class Recorder:
    """Every kernel call the Python filters make while active: (kernel, inputs, outputs, status)."""

    def __init__(self, monkeypatch):
        self.calls: list[tuple[str, list[np.ndarray], list[np.ndarray] | None, int | None]] = []
        bind, run_function = CompiledBackend.bind, CompiledBackend.run_function
        recorder = self

        def recording_bind(backend, kernel, buffers, entry="v"):
            real = bind(backend, kernel, buffers, entry)
            info = backend.kernels[kernel]

            def call() -> int:
                inputs = [np.array(buffers[n], dtype=float).reshape(-1, order="F") for n, _ in info.inputs]
                status = real()
                outputs = [np.array(buffers[n], dtype=float).reshape(-1, order="F") for n, _ in info.outputs[:-1]]
                recorder.calls.append((kernel, inputs, outputs if status == 0 else None, status))
                return status
            return BoundCall(kernel, call)

        def recording_run_function(backend, kernel, diagnostics=False):
            real = run_function(backend, kernel, diagnostics)
            info = backend.kernels[kernel]

            def run(n_steps, *addresses):
                code = real(n_steps, *addresses)
                recorder.add_run(info, n_steps, addresses)
                return code
            return run

        monkeypatch.setattr(CompiledBackend, "bind", recording_bind)
        monkeypatch.setattr(CompiledBackend, "run_function", recording_run_function)

    def add_run(self, info, n_steps: int, addresses) -> None:
        """Expand a ``_run`` call into its steps (carried inputs from the previous step's history)."""
        def read(address, count):
            return np.ctypeslib.as_array((ctypes.c_double * count).from_address(address)).copy() if count else np.zeros(0)
        inputs = {}
        for (name, shape), address in zip(info.inputs, addresses):
            size = shape[0] * shape[1]
            inputs[name] = read(address, n_steps * size).reshape(n_steps, size) if name in info.per_step else \
                read(address, size)
        sizes = dict(info.outputs)
        hist = {name: read(address, n_steps * sizes[name][0] * sizes[name][1]).reshape(n_steps, -1)
                for name, address in zip(info.carried, addresses[len(info.inputs):])}
        status = np.ctypeslib.as_array((ctypes.c_int * n_steps).from_address(addresses[-1])).copy()
        for k in range(n_steps):
            args = []
            for name, _ in info.inputs:
                if name in info.carried:
                    args.append(inputs[name] if k == 0 else hist[name][k - 1])
                elif name in info.per_step:
                    args.append(inputs[name][k])
                else:
                    args.append(inputs[name])
            outputs = [hist[n][k] if n in info.carried else None for n, _ in info.outputs[:-1]]
            self.calls.append((info.name, args, outputs if status[k] == 0 else None, int(status[k])))


def assert_harness_reproduces(nominal, statuses, outputs) -> None:
    """The C harness reproduces the Python side exactly (same code, same inputs): codes and outputs."""
    for i, ((kernel, _, expected, status), got_status, got) in enumerate(zip(nominal, statuses, outputs)):
        assert got_status == status, f"call {i}: {kernel}"
        for e, g in zip(expected or [], got):
            if e is not None:
                np.testing.assert_array_equal(g, e, err_msg=f"call {i}: {kernel}")


def assert_masked_updates_keep_the_state(nominal, extra, statuses, outputs) -> int:
    """All-masked updates among the edge cases leave x and P exactly as they were; their number."""
    masked = 0
    for (kernel, inputs, _, label), status, got in zip(extra, statuses[len(nominal):], outputs[len(nominal):]):
        names = KERNEL_INPUTS[kernel]
        if "update" in kernel and label.startswith("mask="):
            masked += 1
            assert status == 0, kernel
            np.testing.assert_array_equal(got[0], inputs[names.index("x")])
            np.testing.assert_array_equal(got[1], inputs[names.index("P")])
    return masked


def edge_cases(calls) -> list:
    """The documented edge cases, derived from recorded calls (the C contract accepts them and
    answers with a status code): every update/step with all components masked (z = 0 there, as
    the runtime passes it); every MARG call with a zero accelerometer and/or magnetometer sample;
    a zero step (dt = 0); a covariance that is not positive definite (P = 0, P = -P0); and a UKF
    scaling outside its domain (n + kappa = 0 or < 0)."""
    extra = []
    for kernel, inputs, _, _ in calls[::25]:
        names = KERNEL_INPUTS[kernel]
        variants = []
        if "mask" in names:
            variants.append({"mask": 0.0, "z": 0.0})
        variants += [{name: 0.0 for name in zeroed} for zeroed in (("acc",), ("mag",), ("acc", "mag"))
                     if set(zeroed) <= set(names)]
        if "dt" in names:
            variants.append({"dt": 0.0})
        if "P" in names:
            variants += [{"P": 0.0}, {"P": -1.0}]
        if "kappa" in names:
            n = int(round(np.sqrt(inputs[names.index("P")].size)))
            variants += [{"kappa": -float(n)}, {"kappa": -float(n) - 1.0}]
        for change in variants:
            args = [a * change[n] if n == "P" and change.get("P", 0.0) < 0 else
                    np.full_like(a, change[n]) if n in change else a for n, a in zip(names, inputs)]
            extra.append((kernel, args, None, ", ".join(f"{k}={v}" for k, v in change.items())))
    return extra


KERNEL_INPUTS: dict[str, list[str]] = {}


def harness_source(model: str, kernels: dict) -> str:
    names = list(kernels)
    max_args = max(len(k.inputs) + len(k.outputs) - 1 for k in kernels.values())
    rows = []
    for k in kernels.values():
        sizes = [s[0] * s[1] for _, s in k.inputs + k.outputs[:-1]]
        rows.append("{" + ", ".join(map(str, sizes + [0] * (max_args - len(sizes)))) + "}")
    max_total = max(sum(max(s[0] * s[1], 1) for _, s in k.inputs + k.outputs[:-1]) for k in kernels.values())
    return HARNESS.format(model=model, entries=", ".join(f"{model}_{n}_v" for n in names),
                          n_in=", ".join(str(len(kernels[n].inputs)) for n in names),
                          n_out=", ".join(str(len(kernels[n].outputs) - 1) for n in names),
                          max_args=max_args, sizes=", ".join(rows), max_total=max_total)


def replay(tmp_path, compiled, calls, trap: bool = True) -> tuple[np.ndarray, np.ndarray, list]:
    """Run the calls in the harness (traps on, or flags recorded); returns (statuses, raised
    flags, outputs) per call."""
    model, directory = compiled.name, compiled.backend.library_path.parent
    kernels = compiled.backend.kernels
    index = {name: i for i, name in enumerate(kernels)}
    (tmp_path / "harness.c").write_text(harness_source(model, kernels))
    exe = tmp_path / "harness"
    library = compiled.backend.library_path             # the very library Python ran
    proc = subprocess.run(["cc", "-std=gnu99", "-O2", "-Wall", "-Wextra", "-Werror", "-I", str(directory), "-o", str(exe),
                           str(tmp_path / "harness.c"), str(library), f"-Wl,-rpath,{directory}", "-lm"],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    with open(tmp_path / "records.bin", "wb") as handle:
        for kernel, inputs, _, _ in calls:
            np.concatenate([[float(index[kernel])]] + [np.ravel(a) for a in inputs]).astype("<f8").tofile(handle)
    proc = subprocess.run([str(exe), str(tmp_path / "records.bin"), str(tmp_path / "results.bin")]
                          + ([] if trap else ["flags"]),
                          capture_output=True, text=True)
    assert proc.returncode == 0, (f"harness died with code {proc.returncode} (9: a floating-point trap) "
                                  + trapped_record(proc.stderr[-500:], calls, kernels))
    assert proc.stdout.strip() == f"{len(calls)} calls"
    data, offset = np.fromfile(tmp_path / "results.bin", dtype="<f8"), 0
    statuses, flags, outputs = [], [], []
    for kernel, _, _, _ in calls:
        statuses.append(int(data[offset]))
        flags.append(int(data[offset + 1]))
        offset += 2
        outs = []
        for _, shape in kernels[kernel].outputs[:-1]:
            outs.append(data[offset:offset + shape[0] * shape[1]])
            offset += shape[0] * shape[1]
        outputs.append(outs)
    assert offset == data.size
    return np.array(statuses), np.array(flags), outputs


# ---------------------------------------------------------------------- nominal flights
def launcher_flight():
    from symkf.models import launcher as L
    from symkf.scenarios.launcher.campaign import Campaign
    # the default library's run loops (the recorder's; the campaign's own build steps runs in lockstep)
    Campaign(runs=1, seed=0, rates=(20,), duration=L.T_INSERTION, workers=1,
             build={"ekf_lockstep": False, "ukf_lockstep": False}).run()


def attitude_flight():
    from symkf.scenarios.attitude.compare import campaign
    campaign("I", runs=1, duration=300.0, bias_per_axis=np.deg2rad(1.0) / 3600, seed=0, kappa=1.0)


def geo_flight():
    from symkf.scenarios.geo.closed_loop import LoopSettings, simulate
    simulate(LoopSettings(200.0, "ekf", bias=True, noise=True))
    simulate(LoopSettings(100.0, "ekf", failed_gyros=("A", "C")))


def marg_flight():
    from symkf.scenarios.marg.filter import initial_orientation, make_filter, samples
    rng = np.random.default_rng(0)
    n, dt = 2000, 1 / 100
    t = np.arange(n) * dt
    gyro = np.column_stack([0.5 * np.sin(0.7 * t), 0.3 * np.cos(0.4 * t), 0.2 + 0.0 * t]) + 0.01 * rng.standard_normal((n, 3))
    acc = np.array([0.1, -0.2, 9.81]) + 0.05 * rng.standard_normal((n, 3))
    mag = np.array([20.0, 1.0, -40.0]) + 0.5 * rng.standard_normal((n, 3))
    compiled = load("marg")
    for form in ("simple", "full"):
        for mode in ("imu", "marg"):
            f = make_filter(compiled, form)
            z = samples(acc, mag, mode)
            f.x = initial_orientation(compiled, z[0], mode)
            f.run(t, z, mode, u=gyro)


FLIGHTS = {"launcher": launcher_flight, "attitude": attitude_flight, "geo_satellite": geo_flight, "marg": marg_flight}


@pytest.mark.parametrize("model", list(FLIGHTS))
def test_kernels_do_not_trap_on_nominal_flights_and_edge_cases(model, monkeypatch, tmp_path):
    compiled = load(model, backend="compiled")
    recorder = Recorder(monkeypatch)
    FLIGHTS[model]()
    monkeypatch.undo()
    kernels = compiled.backend.kernels
    KERNEL_INPUTS.update({name: [n for n, _ in k.inputs] for name, k in kernels.items()})
    nominal = recorder.calls
    assert len(nominal) > 1000, f"{model}: only {len(nominal)} kernel calls recorded"
    extra = edge_cases(nominal)
    if model == "marg":
        for name in ("gd_initial_imu", "gd_initial_marg"):
            extra.append((name, [np.zeros(shape[0] * shape[1]) for _, shape in kernels[name].inputs], None, None))
    assert extra, "no edge cases derived"
    statuses, _, outputs = replay(tmp_path, compiled, nominal + extra)
    assert_harness_reproduces(nominal, statuses, outputs)
    masked = assert_masked_updates_keep_the_state(nominal, extra, statuses, outputs)
    assert masked or model != "geo_satellite"       # geo's loop calls the update kernels directly


def test_the_harness_does_trap(tmp_path):
    """The harness can fail: an input outside the contract (a state of 1e300) overflows."""
    compiled = load("launcher", backend="compiled")
    kernels = compiled.backend.kernels
    names = [n for n, _ in kernels["ekf_predict"].inputs]
    sizes = {n: s[0] * s[1] for n, s in kernels["ekf_predict"].inputs}
    args = [np.full(sizes[n], 1e300) if n == "x" else np.eye(6).ravel() if n in ("P", "Q") else
            np.full(sizes[n], 0.05) for n in names]
    with pytest.raises(AssertionError, match="floating-point trap"):
        replay(tmp_path, compiled, [("ekf_predict", args, None, "x = 1e300")])


def trapped_record(message: str, calls: list, kernels: dict) -> str:
    """Name the kernel and the inputs of the record the harness trapped on."""
    import re
    match = re.search(r"in record (\d+)", message)
    if not match:
        return message
    kernel, inputs, _, _ = calls[int(match.group(1))]
    names = [n for n, _ in kernels[kernel].inputs]
    return message + f" {kernel}: " + "; ".join(f"{n}={np.array2string(a, precision=3, threshold=8)}"
                                                for n, a in zip(names, inputs))

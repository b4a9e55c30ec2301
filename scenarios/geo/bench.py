"""Model-author loop and step cost of the Koreasat-3 continuous-discrete EKF (paper 003).

    symkf bench geo [--json] [--repeats N] [--opt-levels]

Measures, each as the median of ``--repeats``:

- full build, no-op load and one-line edit (Table 2's I_xy 53 -> 54) -> loaded filter, in this
  process from an empty build folder, as ``symkf bench build`` measures them
  (scenarios/toolchain/build_bench.py; the edit is made in a user's copy of the model, never in this checkout);
- per-call cost of the compiled kernels: ``cd_ekf_predict`` (1/8 s, RK4 of x and P) and each
  ``cd_ekf_update_<sensor>``, both as a bare bound call (ctypes) and through the Python filter
  object, and the NumPy reference for comparison: the three timed in turn in each of 7 rounds
  (the same machine load for all), medians of wall and of thread CPU time, the load average
  printed beside them.

Targets (2-core machine): full build <= 10 s, no-op <= 1 s, a step <= 10 us.
``--opt-levels`` also compiles the generated C at -O1/-O2/-O3 and reports compile times.
``--instructions`` counts, with callgrind (deterministic under load), the instructions per step
of the time update (``cd_ekf_predict``), of the forward run (``cd_ekf_step_gyro_run``: predict
and gyro update) and of the RTS smoother's backward pass (``cd_ekf_smooth_run``), each as the
difference of 600 and 100 steps per 500 (the driver is ``c_loop_driver.c`` beside this file).
"""
from __future__ import annotations

import json
import subprocess
import tempfile
from pathlib import Path

import numpy as np

from symkf.scenarios import callgrind, timing
from symkf.scenarios.report import emit

MODEL = "geo_satellite"
TARGETS = {"full_build_s": 10.0, "noop_build_s": 1.0, "step_us": 10.0}


def add_arguments(parser) -> None:
    parser.add_argument("--json", action="store_true", help="print the results as JSON")
    parser.add_argument("--repeats", type=int, default=1, help="builds per measurement (median)")
    parser.add_argument("--opt-levels", action="store_true", help="also time compiling at -O1/-O2/-O3")
    parser.add_argument("--instructions", action="store_true",
                        help="also count instructions per forward and backward (smoother) step with valgrind")


# ---------------------------------------------------------------------- build loop
def build_loop(repeats: int) -> dict:
    """Cold build, no-op load and one-line edit -> loaded filter (``symkf bench build``'s
    measurement, in this process, from an empty build folder each repeat)."""
    from symkf.scenarios.toolchain.build_bench import measure
    r = measure(MODEL, repeats)
    return {"full_build_s": r["cold_s"], "noop_build_s": r["noop_s"], "edit_build_s": r["edit_s"],
            "edit_phases_s": r["edit_phases_s"], "generated_c_lines": r["generated_c_lines"],
            "samples": {"full": r["samples"]["cold_s"], "noop": r["samples"]["noop_s"], "edit": r["samples"]["edit_s"]}}


def compile_levels(levels=("-O1", "-O2", "-O3")) -> dict:
    """Compile the generated C at several -O levels (strict flags as in the build)."""
    from symkf.codegen.lifecycle import build_model
    from symkf.codegen.c_backend.makefile import STRICT_FLAGS
    result = build_model(MODEL)
    sources = [str(result.directory / name) for name in json.loads(result.manifest.read_text())["sources"]]
    times = {}
    with tempfile.TemporaryDirectory() as tmp:
        for level in levels:
            cmd = ["cc", *STRICT_FLAGS.split(), level, "-fno-math-errno", "-fPIC", "-shared",
                   "-o", str(Path(tmp) / "lib.so"), *sources, "-lm"]
            _, times[level], _ = timing.timed(lambda: subprocess.run(cmd, check=True, capture_output=True))
    return times


# ---------------------------------------------------------------------- step cost
#: Rounds of the step timing (medians over rounds) and calls per round of the compiled paths
#: and of the NumPy reference.
ROUNDS, CALLS, REFERENCE_CALLS = 7, 2000, 50


def _interleaved_us(paths: dict) -> tuple[dict[str, float], dict[str, float]]:
    """Median wall and thread CPU µs per call of each path (``{name: (call, calls per round)}``),
    the paths timed in turn in each of :data:`ROUNDS` rounds so that all see the same load."""
    def block(call, n):
        def calls(i):
            for _ in range(n):
                call()
        return calls
    samples = timing.interleaved({name: block(call, n) for name, (call, n) in paths.items()}, ROUNDS,
                                 {name: n for name, (_, n) in paths.items()})
    return {name: s.us for name, s in samples.items()}, {name: s.cpu_us for name, s in samples.items()}


def step_cost() -> dict:
    """Per kernel: the bare bound call, the filter's method and the NumPy reference, interleaved."""
    from symkf.models import geo_satellite as geo
    from symkf.models import get_model
    from symkf.runtime.reference import NumpyCDEKF
    from symkf.scenarios.geo.closed_loop import _load
    compiled = _load()
    tune = geo.filter_tuning()
    x0 = geo.initial_errors(geo.TABLE6)
    ekf = compiled.filter("cd_ekf", x0, tune["P0"], tune["Q"], R=tune["R"], gate="none")
    reference = NumpyCDEKF(get_model(MODEL), x0, tune["P0"], tune["Q"], tune["R"])
    u = np.array([0.3, -0.1, 0.2, 0.05])
    kernels = {"predict": (ekf.kernel_call("predict"), lambda: ekf.predict(None, 0.125, u=u),
                           lambda: reference.predict(0.0, 0.125, u=u))}
    for name, meas in compiled.model["measurements"].items():
        z = np.zeros(len(meas["outputs"]))
        kernels[f"update_{name}"] = (ekf.kernel_call("update", name),
                                     lambda z=z, name=name: ekf.update(z, measurement=name),
                                     lambda z=z, name=name: reference.update(z, measurement=name))
    out = {}
    for kernel, (bare, method, numpy_call) in kernels.items():
        wall, cpu = _interleaved_us({"bare_call_us": (bare, CALLS), "filter_method_us": (method, CALLS),
                                     "numpy_reference_us": (numpy_call, REFERENCE_CALLS)})
        out[kernel] = {**wall, "cpu_us": cpu}
    return out


# ---------------------------------------------------------------------- instructions
#: Steps of the two callgrind runs whose difference is counted (a gyro update at every step).
FEW_STEPS, MANY_STEPS = 100, 600


def instruction_counts() -> dict:
    """Instructions per step of each part (see the module docstring); {} without valgrind. The
    backward figure is the backward run's count minus the forward run's it starts with."""
    import shutil
    from symkf.codegen.lifecycle import build_model
    if not shutil.which("valgrind"):
        return {}
    directory = build_model(MODEL).directory
    with tempfile.TemporaryDirectory() as tmp:
        exe = callgrind.compile_driver(directory, callgrind.driver_source(__package__, "c_loop_driver.c"),
                                       Path(tmp) / "c_loop")
        stdin = _driver_input(MANY_STEPS)

        def per_step(part: str) -> float:
            totals = []
            for steps in (FEW_STEPS, MANY_STEPS):
                total, stdout = callgrind.run([str(exe), str(steps), part], stdin, Path(tmp) / f"cg.{part}.{steps}")
                if int(stdout.split()[0]):
                    raise RuntimeError(f"geo c_loop_driver: {part} returned code {stdout.split()[0]}")
                totals.append(total)
            return (totals[1] - totals[0]) / (MANY_STEPS - FEW_STEPS)
        counts = {part: per_step(part) for part in ("predict", "run", "backward")}
    counts["backward"] -= counts["run"]
    return {"predict": counts["predict"], "forward_step": counts["run"], "backward_step": counts["backward"],
            "backward_over_forward": counts["backward"] / counts["run"]}


def _driver_input(n_steps: int) -> str:
    """The driver's stdin: Table 6 initial errors (half), the filter tuning, gyro noise and torques."""
    from symkf.models import geo_satellite as geo
    tune = geo.filter_tuning()
    rng = np.random.default_rng(3)
    head = np.concatenate([geo.initial_errors(geo.TABLE6) * 0.5, tune["P0"].ravel("F"), tune["Q"].ravel("F"),
                           tune["R"]["gyro"].ravel("F")])
    rows = [np.concatenate([[0.125], rng.normal(0.0, 0.05, 4), rng.normal(0.0, geo.SIGMA["gyro"], 4)])
            for _ in range(n_steps)]
    return "\n".join([" ".join(f"{v:.17g}" for v in head), str(n_steps)] + [" ".join(f"{v:.17g}" for v in r) for r in rows])


def run(args) -> int:
    load = timing.load_average()
    results = {"model": MODEL, "targets": TARGETS, "build": build_loop(max(args.repeats, 1)), "step": step_cost()}
    results["load_average"] = {"before": load, "after": timing.load_average()}
    if args.opt_levels:
        results["compile_seconds_by_level"] = compile_levels()
    if getattr(args, "instructions", False):
        results["instructions_per_step"] = instruction_counts()
    predict = results["step"]["predict"]["bare_call_us"]
    results["meets_targets"] = {
        "full_build": results["build"]["full_build_s"] <= TARGETS["full_build_s"],
        "noop_build": results["build"]["noop_build_s"] <= TARGETS["noop_build_s"],
        "step": predict <= TARGETS["step_us"]}
    emit(results, None, args.json, _print)
    return 0


def _print(results: dict) -> None:
    b = results["build"]
    print(f"{MODEL}: full build {b['full_build_s']:.2f} s, no-op {b['noop_build_s']:.2f} s, "
          f"after a one-line edit {b['edit_build_s']:.2f} s ({b['generated_c_lines']} lines of C)")
    load = results["load_average"]
    print(f"µs per call, medians of {ROUNDS} interleaved rounds (cpu: the thread's CPU time); load average "
          f"{load['before'][0]:.2f} before, {load['after'][0]:.2f} after")
    print(f"{'kernel':28s} {'bare call us':>13s} {'(cpu)':>7s} {'filter us':>10s} {'(cpu)':>7s} {'numpy us':>10s} {'(cpu)':>7s}")
    for name, row in results["step"].items():
        cpu = row["cpu_us"]
        print(f"{name:28s} {row['bare_call_us']:13.2f} {cpu['bare_call_us']:7.2f} {row['filter_method_us']:10.2f} "
              f"{cpu['filter_method_us']:7.2f} {row['numpy_reference_us']:10.1f} {cpu['numpy_reference_us']:7.1f}")
    for level, seconds in results.get("compile_seconds_by_level", {}).items():
        print(f"compile {level}: {seconds:.2f} s")
    counts = results.get("instructions_per_step")
    if counts:
        print(f"instructions per step (callgrind): predict {counts['predict']:.0f}, forward step (predict + gyro "
              f"update) {counts['forward_step']:.0f}, smoother backward step {counts['backward_step']:.0f} "
              f"({counts['backward_over_forward']:.2f} x forward)")
    elif "instructions_per_step" in results:
        print("instructions per step: valgrind not found")
    print("meets targets:", results["meets_targets"])

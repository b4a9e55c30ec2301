"""Timing and accuracy of the gradient-descent MARG filter (paper 001) on the BROAD trials.

    symkf bench marg [--json] [--repeats 5] [--instructions]

- Build: seconds to generate and compile the ``marg`` bundle from scratch (temporary build dir).
- µs per sample (medians over repeats) for the simplified (31) and full (26)-(30) 9-axis forms:
  ``step_bound`` (one bound C call, inputs already in the buffers: the floor of a per-sample
  call from Python), ``step_api`` (``Filter.step``: argument checks and copies included; the
  C fast path of runtime/fastcall.py; each sample's arrays made before the timed loop, as a
  sensor driver hands them over), ``step_api_indexed`` (the same calls in a loop that indexes the
  recording's arrays for each sample: numpy's ``a[k]`` included, about 1,100 instructions per
  row view), ``step_api_python`` (the calls of
  ``step_api`` with the fast path off: the Python contract path), ``run``
  (``Filter.run``: the C run loop over a whole trial), ``numpy_reference`` (``ReferenceGradientDescent.run``,
  on the first ``--reference-samples`` samples). The three ``step_api`` loops are timed in
  alternate repeats (same machine load).
- The generated multiplicative EKF of ``models/marg_mekf.py`` (``mekf``): µs per sample for
  ``step_bound`` (the bound checked C step, buffers filled), ``step_api``, ``step_api_indexed``
  and ``step_api_python`` (``Filter.step``, as above; after its first step the fast path calls
  the trusted kernel, runtime/fastpath.py) and ``run`` (``Filter.run`` over the whole trial:
  contract checks, masks and the C loop); its BROAD RMSE per trial.
- ``pipeline_vs_vqf``: the whole ``symkf compare marg`` pipeline of the MEKF (masks + run) per
  sample against VQF's ``updateBatch`` on the same trial, side by side (``scenarios/marg/vqf_timing.py``;
  skipped with a message when the vqf package is missing).
- ``--instructions``: the MEKF's C API per sample under callgrind (deterministic; predict, update,
  step and run, and the step kernel's share of the run: ``scenarios/marg/instructions.py``).
- RMSE per BROAD trial (total / heading / inclination over movement phases, deg) at β = 0.041
  (Madgwick's suggested gain) and at the best β of a log sweep (grid of ``compare_marg`` plus 0.041), for both forms.
"""
from __future__ import annotations

import os
import tempfile
from pathlib import Path

from symkf.codegen import build_model
from symkf.models.marg import ALPHA_DEFAULT, BETA_MADGWICK
from symkf.runtime import load
from symkf.runtime.reference.gradient_descent import ReferenceGradientDescent
from symkf.scenarios.marg.filter import initial_orientation, make_filter, samples
from symkf.scenarios import timing
from symkf.scenarios.report import emit
from symkf.scenarios.marg.data import data_dir, load_recording, run_recording
from symkf.scenarios.marg.broad_metric import broad_errors
from . import mekf, mekf_offline
from .instructions import count_instructions
from .compare import SWEEP_BETAS
from .vqf_timing import pipeline_vs_vqf, print_table as print_vqf_table

FORMS = ("simple", "full")


def add_arguments(parser) -> None:
    parser.add_argument("--json", action="store_true", help="print the results as JSON only")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--step-samples", type=int, default=20000, help="samples timed per step repeat")
    parser.add_argument("--reference-samples", type=int, default=2000)
    parser.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    parser.add_argument("--instructions", action="store_true",
                        help="also count the MEKF's instructions per sample in C (callgrind; about a minute)")


def _median_seconds(function, repeats: int) -> float:
    return timing.repeated(function, repeats).median


def cold_build_seconds() -> float:
    """Generate + compile into a fresh temporary build dir (the project's own build is untouched)."""
    saved = os.environ.get("SYMKF_BUILD_DIR")
    with tempfile.TemporaryDirectory() as tmp:
        os.environ["SYMKF_BUILD_DIR"] = tmp
        try:
            return build_model("marg", force=True).seconds
        finally:
            if saved is None:
                os.environ.pop("SYMKF_BUILD_DIR")
            else:
                os.environ["SYMKF_BUILD_DIR"] = saved


def _interleaved_medians(functions: dict, repeats: int) -> dict[str, float]:
    """Median seconds of each function, called in turn ``repeats`` times (same machine load)."""
    samples = timing.interleaved({name: lambda i, f=f: f() for name, f in functions.items()}, repeats)
    return {name: s.median for name, s in samples.items()}


def time_form(compiled, recording, form: str, args) -> dict:
    n_step = min(args.step_samples, len(recording))
    z = samples(recording.acc, recording.mag)
    filt = make_filter(compiled, form, beta=BETA_MADGWICK, q0=initial_orientation(compiled, z[0]))
    bound = filt.kernel_call("step", "marg")   # the raw bound kernel call (buffers already filled)
    time_, dt, gyro = recording.time, recording.dt, recording.gyro

    def raw_steps():
        for _ in range(n_step):
            bound()

    python = make_filter(compiled, form, beta=BETA_MADGWICK, q0=filt.x)
    python.fast_path = False
    per_sample = [(time_[k - 1], dt[k], z[k], gyro[k]) for k in range(1, n_step)]   # dt[0] = 0: a run's start
    start = {f: (f.x.copy(), f.t) for f in (filt, python)}

    def restart(f):
        """Each timed loop steps the trial from its start: the filter back to its first state and time."""
        f.x, f.t = start[f][0], start[f][1]

    def api_steps(f=filt):
        restart(f)
        for t_k, dt_k, z_k, gyro_k in per_sample:
            f.step(t_k, dt_k, z_k, "marg", u=gyro_k)

    def indexed_steps(f=filt):
        restart(f)
        for k in range(1, n_step):
            f.step(time_[k - 1], dt[k], z[k], "marg", u=gyro[k])

    def whole_run():
        restart(filt)
        filt.run(time_, z, "marg", u=gyro)

    m = min(args.reference_samples, len(recording))
    q0 = initial_orientation(compiled, z[0])

    def reference():
        ReferenceGradientDescent("marg", f"gd_{form}", q0, p=[BETA_MADGWICK, ALPHA_DEFAULT]).run(
            time_[:m], z[:m], "marg", u=gyro[:m])

    steps = _interleaved_medians({"api": api_steps, "indexed": indexed_steps, "python": lambda: api_steps(python)},
                                 args.repeats)
    return {
        "step_bound_us": _median_seconds(raw_steps, args.repeats) / n_step * 1e6,
        **_per_step(steps, n_step - 1),
        "run_us": _median_seconds(whole_run, args.repeats) / len(recording) * 1e6,
        "numpy_reference_us": _median_seconds(reference, max(1, args.repeats // 2)) / m * 1e6,
    }


def time_mekf(compiled, recording, args) -> dict:
    """µs per sample of the generated MARG MEKF: bound C step, Filter.step, whole-trial run."""
    n_step = min(args.step_samples, len(recording))
    filt = mekf.make_filter(compiled, recording)
    z, mag, mask = mekf.measurements(recording), recording.mag, mekf.masks(recording)
    x0, P0 = filt.x.copy(), filt.P.copy()
    filt.step(0.0, recording.dt[1], z[1], "marg", q=mag[1], mask=mask[1], u=recording.gyro[1])
    bound = filt.kernel_call("step", "marg")

    def raw_steps():
        for _ in range(n_step):
            bound()

    python = mekf.make_filter(compiled, recording)
    python.fast_path = False

    time, dt, gyro = recording.time, recording.dt, recording.gyro
    samples = [(time[k - 1], dt[k], z[k], mag[k], mask[k], gyro[k]) for k in range(1, n_step)]

    def restart(f):
        """Each timed loop steps the trial from its start: the filter back to its first state and time."""
        f.x, f.P, f.t = x0, P0, float(time[0])

    def api_steps(f=filt):
        restart(f)
        for t_k, dt_k, z_k, mag_k, mask_k, gyro_k in samples:
            f.step(t_k, dt_k, z_k, "marg", q=mag_k, mask=mask_k, u=gyro_k)

    def indexed_steps(f=filt):
        restart(f)
        for k in range(1, n_step):
            f.step(time[k - 1], dt[k], z[k], "marg", q=mag[k], mask=mask[k], u=gyro[k])

    def whole_run():
        restart(filt)
        filt.run(recording.time, z, "marg", q=mag, mask=mask, u=recording.gyro)

    steps = _interleaved_medians({"api": api_steps, "indexed": indexed_steps, "python": lambda: api_steps(python)},
                                 args.repeats)
    return {"step_bound_us": _median_seconds(raw_steps, args.repeats) / n_step * 1e6, **_per_step(steps, n_step - 1),
            "run_us": _median_seconds(whole_run, args.repeats) / len(recording) * 1e6}


def _per_step(steps: dict[str, float], calls: int) -> dict[str, float]:
    """µs per call of the three ``step_api`` loops (:func:`_interleaved_medians` seconds)."""
    return {"step_api_us": steps["api"] / calls * 1e6, "step_api_indexed_us": steps["indexed"] / calls * 1e6,
            "step_api_python_us": steps["python"] / calls * 1e6}


def accuracy(compiled, recording, form: str) -> dict:
    rows = {}
    for beta in [BETA_MADGWICK] + SWEEP_BETAS.tolist():
        run = run_recording(compiled, make_filter(compiled, form, beta=beta), recording)
        rows[float(beta)] = broad_errors(run.q, recording)
    best = min(rows, key=lambda b: rows[b]["total"])          # over the sweep grid and 0.041
    return {"beta_0.041": rows[BETA_MADGWICK], "best_beta": float(best), "best": rows[float(best)]}


def run(args) -> int:
    trials = sorted((data_dir() / "broad").glob("*.mat"))
    if not trials:
        print(f"symkf bench marg: no BROAD trials in {data_dir() / 'broad'}")
        return 1
    result = {"build_seconds": cold_build_seconds(), "timing_trial": trials[0].stem, "timing_us_per_sample": {},
              "rmse_deg": {}, "notes": "medians; 9-axis; machine shared, numbers are indicative"}
    compiled = load("marg", backend="compiled")
    first = load_recording(trials[0])
    for form in FORMS:
        result["timing_us_per_sample"][form] = time_form(compiled, first, form, args)
    mekf_model = load("marg_mekf", backend="compiled")
    result["timing_us_per_sample"]["mekf"] = time_mekf(mekf_model, first, args)
    result["pipeline_vs_vqf"] = pipeline_vs_vqf(mekf_model, mekf_offline.load_model(), first, args.repeats)
    if getattr(args, "instructions", False):
        result["mekf_instructions_per_sample"] = count_instructions(build_model("marg_mekf").directory, first)
    result["mekf_rmse_deg"] = {}
    for path in trials:
        recording = first if path == trials[0] else load_recording(path)
        result["rmse_deg"][path.stem] = {form: accuracy(compiled, recording, form) for form in FORMS}
        result["mekf_rmse_deg"][path.stem] = broad_errors(mekf.run_recording(mekf_model, recording).q, recording, frame="enu")
    emit(result, args.out, args.json, _print_tables)
    return 0


def _print_tables(result: dict) -> None:
    print(f"build (generate + compile, cold): {result['build_seconds']:.2f} s")
    print(f"\nus per sample ({result['timing_trial']}):")
    print(f"{'form':8} {'step (bound)':>13} {'step (API)':>11} {'(indexed)':>10} {'(Python path)':>14} {'run':>8} "
          f"{'NumPy ref':>10} {'ref/run':>8}")
    for form, t in result["timing_us_per_sample"].items():
        reference = (f"{t['numpy_reference_us']:10.1f} {t['numpy_reference_us'] / t['run_us']:8.0f}"
                     if "numpy_reference_us" in t else f"{'-':>10} {'-':>8}")
        print(f"{form:8} {t['step_bound_us']:13.3f} {t['step_api_us']:11.2f} {t['step_api_indexed_us']:10.2f} "
              f"{t['step_api_python_us']:14.2f} {t['run_us']:8.3f} {reference}")
    print_vqf_table(result["pipeline_vs_vqf"], result["timing_trial"])
    counts = result.get("mekf_instructions_per_sample")
    if counts:
        print(f"\nmekf instructions per sample (callgrind, {result['timing_trial']}, C API): "
              + ", ".join(f"{part} {counts[part]:.0f}" for part in ("predict", "update", "step", "run"))
              + f"; run's step kernels {counts['run_kernel']:.0f}, loop checks and copies "
              f"{counts['run'] - counts['run_kernel']:.0f} (samples 1000-3000, at rest); whole trial: run "
              f"{counts['run_trial']:.0f}, kernels {counts['run_trial_kernel']:.0f}")
    elif "mekf_instructions_per_sample" in result:
        print("\nmekf instructions per sample: valgrind not found")
    print("\nBROAD RMSE total/heading/inclination [deg], movement phases:")
    for trial, forms in result["rmse_deg"].items():
        for form, r in forms.items():
            a, b = r["beta_0.041"], r["best"]
            print(f"{trial:36} {form:6} beta=0.041: {a['total']:5.2f}/{a['heading']:5.2f}/{a['inclination']:5.2f}"
                  f"   best beta={r['best_beta']:<8g}: {b['total']:5.2f}/{b['heading']:5.2f}/{b['inclination']:5.2f}")
        m = result["mekf_rmse_deg"][trial]
        print(f"{trial:36} mekf   (models/marg_mekf.py, one parameter set): "
              f"{m['total']:5.2f}/{m['heading']:5.2f}/{m['inclination']:5.2f}")

"""Instructions per sample of the generated MARG MEKF in C (callgrind; deterministic, unlike wall
time on a shared machine): ``symkf bench marg --instructions``.

A small C program (compiled against the bundle's library with its flags) feeds a BROAD trial's
samples to one part of the filter's C API:

- ``predict``: ``marg_mekf_mekf_predict`` per sample (its wrapper's checks included);
- ``update``: ``marg_mekf_mekf_update_marg`` per sample (the same);
- ``step``: ``marg_mekf_mekf_step_marg``, predict + update in one call;
- ``run``: ``marg_mekf_mekf_run_marg_run`` over the samples (the loop in C; it iterates the step
  without the diagnostics y, S: ``FilterSpec.run``, and after the first successful step that
  step without the checks its own state cannot fail: ``Kernel.trusted``).

Each part is counted over 3000 and over 1000 samples; the difference / 2000 is its cost per
sample without start-up. Those samples are the trial's initial rest (every component used but the
heading at times); ``run_trial`` counts the run from sample 1000 to the end of the trial, with
the mask patterns of the whole recording (the kernels specialised per mask pattern show there). For ``run`` the kernels' own share (callgrind's inclusive counts of
``marg_mekf_k_mekf_run_marg`` and of its trusted partner and variants, which the loop iterates once
a step has succeeded) is reported too: the rest is the loop's checks and copies.
"""
from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import numpy as np

from symkf.models import marg_mekf
from symkf.scenarios import callgrind
from . import mekf

PARTS = ("predict", "update", "step", "run")
#: The kernels a run iterates (C names start with it): the checked one until a step succeeds, then its
#: trusted partner or one of that partner's variants (per mask pattern, gate off).
RUN_KERNELS = "marg_mekf_k_mekf_run_marg"
SAMPLES = (1000, 3000)
#: The C program that feeds the samples to one part of the API (beside this file).
C_DRIVER = "mekf_driver.c"



def count_instructions(directory: Path, recording, whole_trial: bool = True) -> dict:
    """{part: instructions per sample} and ``run_kernel`` (the run kernel's share inside the run);
    ``whole_trial``: also ``run_trial`` and ``run_trial_kernel``, the run from sample 1000 to the
    end of the recording (every mask pattern in its proportion, unlike samples 1000-3000, which
    are BROAD's initial rest)."""
    if shutil.which("valgrind") is None:
        return {}
    with tempfile.TemporaryDirectory() as tmp:
        exe = callgrind.compile_driver(directory, callgrind.driver_source(__package__, C_DRIVER), Path(tmp) / "mekf_driver")
        data = _driver_input(recording, max(SAMPLES))
        out = {}
        for part in PARTS:
            counts = [_callgrind(exe, part, n, data, Path(tmp)) for n in SAMPLES]
            out[part] = (counts[1][0] - counts[0][0]) / (SAMPLES[1] - SAMPLES[0])
            if part == "run":
                out["run_kernel"] = (counts[1][1] - counts[0][1]) / (SAMPLES[1] - SAMPLES[0])
        if whole_trial:
            n = len(recording)
            data = _driver_input(recording, n)
            counts = [_callgrind(exe, "run", m, data, Path(tmp)) for m in (SAMPLES[0], n)]
            out["run_trial"] = (counts[1][0] - counts[0][0]) / (n - SAMPLES[0])
            out["run_trial_kernel"] = (counts[1][1] - counts[0][1]) / (n - SAMPLES[0])
        return out


def _driver_input(recording, count: int) -> bytes:
    n = min(count, len(recording))
    x0 = np.r_[mekf.initial_orientation(recording.acc[0], recording.mag[0]), np.zeros(3)]
    P0 = np.diag(mekf.INITIAL_SIGMA ** 2)
    sigma = [marg_mekf.ACC_DIRECTION_SIGMA] * 3 + [marg_mekf.HEADING_SIGMA] + [marg_mekf.REST_GYRO_SIGMA] * 3
    head = np.concatenate([x0, P0.ravel("F"), marg_mekf.process_noise_psd().ravel("F"),
                           np.diag(np.square(sigma)).ravel("F"), np.zeros(7)])
    times = recording.time[:n]
    t, dt = np.concatenate([times[:1], times[:-1]]), np.diff(times, prepend=times[:1])
    mask = mekf.masks(recording)[:n]
    z = np.where(mask > 0.5, mekf.measurements(recording)[:n], 0.0)
    rows = np.column_stack([t, dt, recording.gyro[:n], recording.mag[:n], z, mask])
    return np.concatenate([head, rows.ravel()]).astype("<f8").tobytes()


def _callgrind(exe: Path, part: str, n: int, data: bytes, tmp: Path) -> tuple[int, int]:
    """(all instructions, inclusive instructions of the run kernel) of one driver run."""
    out = tmp / f"cg.{part}.{n}"
    total, stdout = callgrind.run([str(exe), part, str(n)], data, out)
    if int(stdout.split()[0]) not in (0, 6):
        raise RuntimeError(f"mekf driver: {part} returned code {stdout.decode().strip()}")
    counts = callgrind.function_counts(out, inclusive=True, threshold=None)
    return total, sum(count for name, count in counts.items() if name.startswith(RUN_KERNELS))

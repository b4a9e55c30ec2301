"""The MARG pipeline of ``symkf compare marg`` against VQF on the same trial, timed side by side:
``symkf bench marg`` (VQF: Laidig & Seel, "VQF: Highly accurate IMU orientation estimation with
bias estimation and magnetic disturbance rejection", Information Fusion 91, 2023; the ``vqf``
package, an optional bench dependency: ``pip install 'symkf[bench]'``).

Per sample, in interleaved rounds (the same machine load for all):

- ``pipeline``: :func:`symkf.scenarios.marg.mekf.run_recording` — the availability masks and
  measurements from the raw samples (the preprocessing) and the generated MEKF's whole-trial run;
- ``vqf``: ``VQF(Ts).updateBatch(gyr, acc, mag)`` — VQF's online filter over the trial in C++;
- ``pipeline_smoothed`` and ``offline_vqf``: the offline pass (``mekf_offline.smooth_recording``:
  its masks, the forward run and the error-state RTS smoother) and VQF's offline form
  (``offlineVQF``, defaults).

``ratio`` is pipeline / vqf per round (median, min, max): below 1 the pipeline is the faster.
"""
from __future__ import annotations

import numpy as np

from symkf.scenarios import timing
from . import mekf, mekf_offline

#: Said when the vqf package is absent (the comparison is skipped, nothing else).
MISSING = "vqf is not installed: pip install vqf (or 'symkf[bench]') to time the pipeline against VQF"


def vqf_or_none():
    """The vqf module, or None when it is not installed."""
    try:
        import vqf
    except ImportError:
        return None
    return vqf


def pipeline_vs_vqf(compiled, offline, recording, rounds: int) -> dict:
    """µs per sample (medians over ``rounds``) of the pipeline and VQF, and their per-round
    ratios; ``compiled``: ``marg_mekf``, ``offline``: ``mekf_offline.load_model()``;
    ``{"skipped": MISSING}`` without the vqf package."""
    vqf = vqf_or_none()
    if vqf is None:
        return {"skipped": MISSING}
    ts = float(np.median(np.diff(recording.time)))
    gyr, acc, mag = (np.ascontiguousarray(a, dtype=float) for a in (recording.gyro, recording.acc, recording.mag))
    functions = {
        "pipeline": lambda i: mekf.run_recording(compiled, recording),
        "vqf": lambda i: vqf.VQF(ts).updateBatch(gyr, acc, mag),
        "pipeline_smoothed": lambda i: mekf_offline.smooth_recording(offline, recording),
        "offline_vqf": lambda i: vqf.offlineVQF(gyr, acc, mag, ts),
    }
    samples = timing.interleaved(functions, rounds)
    n = len(recording)
    out = {f"{name}_us": s.median / n * 1e6 for name, s in samples.items()}
    for name, num, den in (("ratio", "pipeline", "vqf"), ("ratio_smoothed", "pipeline_smoothed", "offline_vqf")):
        ratios = timing.round_ratios(samples[num], samples[den])
        out[name] = {"median": float(np.median(ratios)), "min": min(ratios), "max": max(ratios)}
    out["samples"] = n
    return out


def print_table(result: dict, trial: str) -> None:
    if "skipped" in result:
        print(f"\npipeline vs VQF: skipped ({result['skipped']})")
        return
    print(f"\npipeline vs VQF, us per sample ({trial}, {result['samples']} samples, interleaved rounds):")
    print(f"  online:  symkf compare marg pipeline (masks + MEKF run) {result['pipeline_us']:.3f}, "
          f"VQF updateBatch {result['vqf_us']:.3f}, ratio {_ratio(result['ratio'])}")
    print(f"  offline: pipeline + RTS smoother {result['pipeline_smoothed_us']:.3f}, "
          f"offlineVQF {result['offline_vqf_us']:.3f}, ratio {_ratio(result['ratio_smoothed'])}")


def _ratio(r: dict) -> str:
    return f"{r['median']:.2f} (min {r['min']:.2f}, max {r['max']:.2f})"

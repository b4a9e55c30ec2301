"""``symkf bench marg``'s side-by-side timing of the MARG pipeline against VQF
(scenarios/marg/vqf_timing.py): figures per sample and per-round ratios, or a clear skip."""
import sys

import numpy as np
import pytest

from symkf.runtime import load
from symkf.scenarios.marg import mekf_offline, vqf_timing
from symkf.scenarios.marg.data import Recording


def _recording(n: int = 3000) -> Recording:
    rng = np.random.default_rng(5)
    time = np.arange(n) / 285.714
    gyro = rng.normal(0, 2e-3, (n, 3)) + np.where(time[:, None] > 2.0, [0.2, -0.1, 0.5], 0.0)
    acc = rng.normal([0.0, 0.0, 9.81], 0.05, (n, 3))
    mag = rng.normal([0.0, 25.0, -43.0], 0.3, (n, 3))
    return Recording("synthetic", time, gyro, acc, mag)


def test_pipeline_vs_vqf_gives_per_sample_figures_and_round_ratios():
    pytest.importorskip("vqf", reason="vqf is not installed (pip install 'symkf[bench]')")
    recording = _recording()
    result = vqf_timing.pipeline_vs_vqf(load("marg_mekf"), mekf_offline.load_model(), recording, rounds=3)
    assert result["samples"] == len(recording)
    for name in ("pipeline", "vqf", "pipeline_smoothed", "offline_vqf"):
        assert 0 < result[f"{name}_us"] < 1e4, (name, result)
    for name in ("ratio", "ratio_smoothed"):
        r = result[name]
        assert 0 < r["min"] <= r["median"] <= r["max"]


def test_pipeline_vs_vqf_says_what_is_missing(monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "vqf", None)             # import vqf raises ImportError
    assert vqf_timing.vqf_or_none() is None
    result = vqf_timing.pipeline_vs_vqf(None, None, _recording(10), rounds=1)
    assert result == {"skipped": vqf_timing.MISSING}
    vqf_timing.print_table(result, "synthetic")
    assert "pip install vqf" in capsys.readouterr().out

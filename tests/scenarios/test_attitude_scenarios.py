"""`symkf compare attitude` and `symkf bench attitude` on tiny settings (campaigns: the CLI)."""
import argparse
import json
import re

import numpy as np
import pytest

from symkf.models import attitude as att
from symkf.scenarios import results
from symkf.scenarios.cli import main
from symkf.scenarios.attitude import bench as bench_attitude, compare as compare_attitude


def parse(module, argv):
    parser = argparse.ArgumentParser()
    module.add_arguments(parser)
    return parser.parse_args(argv)


def test_truth_record_is_consistent():
    simulator = compare_attitude.TruthSimulator(duration=60.0)
    record = simulator.simulate(np.random.default_rng(0), np.full(3, 4e-3), star_period=2.0)
    assert record.q_true.shape == (240, 4) and record.omega_g.shape == (240, 3)
    assert np.abs(np.linalg.norm(record.q_true, axis=1) - 1).max() < 1e-15
    assert np.isfinite(record.star).all(axis=1).sum() == 30             # one sample every 2 s
    # the gyro reads the true rate minus the bias (eq 28): mean offset ≈ -4e-3 rad/s per axis
    offset = record.omega_g - compare_attitude.true_body_rate((np.arange(240) + 0.5) * 0.25)
    assert np.allclose(offset.mean(axis=0), -4e-3, atol=3 * att.GYRO_ANGLE_RANDOM_WALK / np.sqrt(0.25 * 240) + 1e-5)


def test_compare_writes_figures_and_summary(tmp_path, monkeypatch, capsys):
    args = parse(compare_attitude, ["--scenario", "I", "--runs", "2", "--duration", "300", "--out", str(tmp_path)])
    assert compare_attitude.run(args) == 0
    printed = capsys.readouterr().out
    assert "HOLDS: both filters converge — runs converged: MEKF 2/2, UKF 2/2." in printed
    assert re.search(r"in [\d.]+ s: build [\d.]+ s, campaign [\d.]+ s, figures and series [\d.]+ s\n$", printed)
    out = tmp_path / "scenario_I"
    series = results.load(out)                  # the figures' series and every run's row
    assert series.comparison == "attitude" and series["attitude_error_rms"].shape == (2, 1200)
    assert series.variables["attitude_error_rms"].attrs["units"] == "deg"
    assert series["run_failed_steps"].tolist() == [[0, 0], [0, 0]] and series["run_converged"].all()
    # symkf plot redraws both figures from the series alone, byte for byte, without a filter
    monkeypatch.setattr(compare_attitude, "one_run", lambda *a: pytest.fail("symkf plot ran a filter"))
    assert main(["plot", str(tmp_path), "--out", str(tmp_path / "again")]) == 0
    for name in ("fig_attitude_error.png", "fig_bias_error.png"):
        assert (tmp_path / "again" / "scenario_I" / name).read_bytes() == (out / name).read_bytes()
    assert (out / "fig_attitude_error.png").stat().st_size > 10_000
    assert (out / "fig_bias_error.png").stat().st_size > 10_000
    summary = json.loads((out / "summary.json").read_text())
    for name in ("mekf", "ukf"):
        metrics = summary["filters"][name]
        assert metrics["converged"] and metrics["failed_steps_total"] == 0
        assert 1e-3 < metrics["attitude_rms_deg"] < 0.5          # from 10 deg down to star-tracker level
        assert metrics["attitude_3sigma_deg"] >= 3 * metrics["attitude_rms_deg"] / np.sqrt(3) - 1e-12
    assert np.isfinite(summary["ukf_improvement_percent"])
    assert summary["paper_claims"]["ukf_about_30_percent_better"]["claimed_percent"] == 30.0
    about = summary["paper_claims"]["ukf_about_30_percent_better"]
    assert about["holds"] == (abs(summary["ukf_improvement_percent"] - 30) <= 10)
    assert f"{summary['ukf_improvement_percent']:.1f} %" in about["compared"]
    assert summary["paper_claims"]["both_converge"]["compared"] == "runs converged: MEKF 2/2, UKF 2/2"
    rms = np.sqrt(np.mean(series["attitude_error_rms"][:, 600:] ** 2, axis=1))     # the last half, over runs
    assert rms.tolist() == pytest.approx([summary["filters"][f]["attitude_rms_deg"] for f in ("mekf", "ukf")], rel=1e-12)
    rts, mekf = summary["filters"]["mekf_rts"], summary["filters"]["mekf"]
    assert rts["failed_steps_total"] == 0                                # no refused backward step
    assert rts["attitude_rms_deg"] < mekf["attitude_rms_deg"]            # the whole record helps
    assert rts["transient_rms_deg_first_300s"] < 0.5 * mekf["transient_rms_deg_first_300s"]
    assert all(summary["rts_le_filter"].values())


def test_scenario_two_reports_the_literal_bias(tmp_path):
    args = parse(compare_attitude, ["--scenario", "II", "--runs", "1", "--duration", "120", "--out", str(tmp_path)])
    assert compare_attitude.run(args) == 0
    summary = json.loads((tmp_path / "scenario_II" / "summary.json").read_text())
    assert summary["initial_bias_rad_s_per_axis"] == pytest.approx(np.deg2rad(2.0))
    assert summary["literal_bias"]["initial_bias_rad_s_per_axis"] == 2.0
    assert not summary["literal_bias"]["filters"]["mekf"]["converged"]       # 2 rad/s: far outside P0


def test_bench_reports_sigma_points_and_timings(capsys):
    args = parse(bench_attitude, ["--json", "--steps", "20", "--repeats", "1", "--reference-steps", "2"])
    assert bench_attitude.run(args) == 0
    results = json.loads(capsys.readouterr().out)
    assert results["ukf"]["sigma_points"]["propagation"] == 25
    assert results["ukf"]["sigma_points"]["update"] == 19
    assert results["aukf"]["sigma_points"]["propagation"] == 31
    for kind in ("mekf", "ukf", "aukf"):
        assert results[kind]["kernel_step_with_update_us"] > 0 and results[kind]["numpy_reference_propagate_us"] > 0


def test_paper_like_preset_scales_the_mekf_process_noise_only(tmp_path):
    """Issue 11: the paper's "about 30 %" needs the MEKF's Q 16x the UKF's; with equal noise the
    two filters coincide (the same draws: run k's stream depends on (seed, k) only)."""
    common = ["--scenario", "I", "--runs", "2", "--duration", "600", "--seed", "3"]
    results = {}
    for preset in ("correct", "paper-like"):
        args = parse(compare_attitude, [*common, "--filters", preset, "--out", str(tmp_path / preset)])
        assert compare_attitude.run(args) == 0
        results[preset] = json.loads((tmp_path / preset / "scenario_I" / "summary.json").read_text())
    correct, paper = results["correct"], results["paper-like"]
    assert correct["mekf_over_ukf_q_ratio"] == 1 and paper["mekf_over_ukf_q_ratio"] == 16
    assert abs(correct["ukf_improvement_percent"]) < 0.1
    assert paper["ukf_improvement_percent"] > 10
    assert paper["filters"]["ukf"]["attitude_rms_deg"] == pytest.approx(correct["filters"]["ukf"]["attitude_rms_deg"])
    for name in ("mekf", "ukf"):
        metrics = paper["filters"][name]
        assert metrics["transient_rms_deg_first_300s"] > 0
        assert "transient_rms_deg_first_1000s" not in metrics      # a 600 s run has no 1000 s window
        assert 0 < metrics["time_to_1deg_s"] <= metrics["time_to_0.1deg_s"]


@pytest.mark.parametrize("bad", [["--mekf-q-scale", "0"], ["--ukf-r-scale", "-1"], ["--mekf-r-scale", "nan"]])
def test_bad_noise_scales_are_refused(tmp_path, bad):
    args = parse(compare_attitude, ["--runs", "1", "--duration", "10", "--out", str(tmp_path), *bad])
    with pytest.raises(SystemExit, match="must be a positive number"):
        compare_attitude.run(args)
    assert not (tmp_path / "scenario_I").exists()

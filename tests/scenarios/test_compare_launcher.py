"""`symkf compare launcher` end to end on a short horizon, and the campaign's reproducibility."""
import csv
import json

import numpy as np
import pytest

from symkf.codegen import make_config
from symkf.codegen.c_backend import lockstep
from symkf.scenarios.launcher import campaign as C
from symkf.scenarios.cli import main


@pytest.fixture(scope="module")
def short_campaign(tmp_path_factory, launcher_compiled):
    out = tmp_path_factory.mktemp("launcher")
    assert main(["compare", "launcher", "--runs", "3", "--duration", "60", "--seed", "5",
                 "--out", str(out), "--quiet"]) == 0
    return out


def test_outputs_are_written_and_well_formed(short_campaign):
    out = short_campaign
    for name in ("rms_table.csv", "rms_table.md", "fig_velocity_rms.png", "fig_radius_rms.png",
                 "fig_nees.png", "fig_smoother_rms.png", "summary.json"):
        assert (out / name).stat().st_size > 0, name
    rows = list(csv.DictReader(open(out / "rms_table.csv")))
    assert len(rows) == 24 and set(rows[0]) == {"state", "unit", "case", "ekf", "ukf", "paper_ekf", "paper_ukf",
                                                "ekf_rts", "ukf_rts"}
    assert {r["unit"] for r in rows} == {"m/s", "deg", "m"}
    assert all(np.isfinite(float(r[k])) and float(r[k]) > 0 for r in rows for k in ("ekf", "ukf"))
    table = (out / "rms_table.md").read_text()
    assert "| r (m) |" in table and "(0.535)" in table       # paper's 20 Hz small UKF r beside ours
    assert table.splitlines()[0] == f"Filters: correct; arithmetic: {C.Campaign(3, 5).arithmetic()}"
    summary = json.loads((out / "summary.json").read_text())
    case = summary["cases"]["20Hz small"]["ukf"]
    assert set(case) >= {"rms_eq11", "mean_nees", "fraction_inside_band", "wall_s", "steps"}
    assert case["steps"] == 3 * 1201
    claim = summary["claims"]["ukf_le_ekf_every_state_10Hz_large"]
    assert isinstance(claim["holds"], bool) and claim["says"].startswith("the UKF is at least as accurate")
    assert "10Hz large" in claim["compared"]
    # the campaign's CPU (this process's threads did every run: at least the runs' own CPU)
    assert summary["executor"].startswith("threads") and summary["workers"] >= 1
    run_cpu = sum(summary["cases"][label][f]["cpu_s"] for label in summary["cases"] for f in C.FILTERS)
    assert summary["campaign_cpu_s"] >= run_cpu > 0


def test_numbers_are_plausible(short_campaign):
    summary = json.loads((short_campaign / "summary.json").read_text())
    for label, case in summary["cases"].items():
        for family in ("ekf", "ukf"):
            assert case[family]["failed_steps"] == 0
            # consistent within an order of magnitude of the 6 expected, except the EKF after a
            # large initial error near vertical lift-off (heading poorly observable): a finding
            if family == "ukf" or "small" in label:
                assert 0.5 < case[family]["mean_nees"] < 60, (label, family)
    ukf_20 = summary["cases"]["20Hz small"]["ukf"]["rms_eq11"]
    assert ukf_20["r"] < 100 and ukf_20["V"] < 5          # m, m/s over the first minute


def test_tuning_options_reach_the_filters(tmp_path, launcher_compiled):
    assert main(["compare", "launcher", "--runs", "1", "--duration", "5", "--rates", "20", "--kappa", "1",
                 "--q-scale", "10", "--out", str(tmp_path), "--quiet"]) == 0
    tuning = json.loads((tmp_path / "summary.json").read_text())["tuning"]
    assert tuning["kappa"] == 1.0 and tuning["Q"][0][0] == pytest.approx(10 * C.TUNING["Q"][0, 0])
    assert main(["compare", "launcher", "--kappa", "-6", "--quiet", "--out", str(tmp_path)]) == 2


@pytest.mark.parametrize("bad", [["--p0-floor", "1,2,3"], ["--p0-floor", "1,1,1,1,1,-1"], ["--p0-floor", "a,b"],
                                 ["--ekf-q-scale", "0"], ["--ukf-q-scale", "nan"], ["--rates", "15"],
                                 ["--rates", ","]])
def test_bad_knobs_are_refused_before_any_work(tmp_path, bad, capsys):
    assert main(["compare", "launcher", "--quiet", "--out", str(tmp_path / "x"), *bad]) == 2
    assert "symkf compare launcher:" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_per_filter_knobs_reach_one_filter_only(tmp_path, launcher_compiled):
    assert main(["compare", "launcher", "--runs", "1", "--duration", "5", "--rates", "20", "--ekf-q-scale", "1e6",
                 "--p0-floor", "2,1e-4,1e-4,100,1e-5,1e-5", "--out", str(tmp_path), "--quiet"]) == 0
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["filters"] == "correct" and summary["tuning"]["ekf_q_scale"] == 1e6
    assert summary["tuning"]["P0_floor"][0] == 2.0
    small = summary["cases"]["20Hz small"]
    assert small["ekf"]["rms_eq11"]["V"] != small["ukf"]["rms_eq11"]["V"]   # the filters now differ
    assert (small["ekf"]["runs"], small["ekf"]["diverged_run_count"], small["ekf"]["excursion_run_count"]) == (1, 0, 0)
    assert small["ekf"]["fraction_inside_band_outside_event_windows"] is None   # 5 s: all in the lift-off window


def test_summary_reports_distance_to_paper_and_consistency(short_campaign):
    summary = json.loads((short_campaign / "summary.json").read_text())
    rows = list(csv.DictReader(open(short_campaign / "rms_table.csv")))
    expected = np.mean([abs(np.log10(float(r[f]) / float(r["paper_" + f]))) for r in rows for f in ("ekf", "ukf")])
    assert summary["mean_abs_log10_vs_paper"] == pytest.approx(expected) and summary["table3_cells"] == 48
    for case in summary["cases"].values():
        for family in ("ekf", "ukf"):
            assert 0 <= case[family]["fraction_inside_band_outside_event_windows"] <= 1
            assert case[family]["runs"] == 3


def test_same_seed_same_draws_different_seed_different_draws(launcher_compiled):
    track = C.radar_track(np.arange(5) * 0.05, C.propagate(np.arange(5) * 0.05))
    one, same, other = C.Campaign(1, 11), C.Campaign(1, 11, rates=(20,)), C.Campaign(1, 12)
    case = C.Case(20, "small")
    np.testing.assert_array_equal(one.measurements(case, 0, track), same.measurements(case, 0, track))
    assert not np.array_equal(one.measurements(case, 0, track), other.measurements(case, 0, track))
    assert not np.array_equal(one.measurements(case, 0, track), one.measurements(case, 1, track))
    assert not np.array_equal(one.measurements(case, 0, track), one.measurements(C.Case(20, "large"), 0, track))


def test_campaign_repeats_exactly(launcher_compiled):
    results = [C.Campaign(2, 3, rates=(10,), duration=20.0).run() for _ in range(2)]
    for a, b in zip(*results):
        for family in C.FILTERS:
            np.testing.assert_array_equal(a.errors[family].rms(), b.errors[family].rms())


def test_series_file_holds_the_time_series_and_every_run_summary_json_none(short_campaign):
    """RMS(t) and NEES(t) per case, estimate, state and time, and one row per run, in the series
    file with dims and units; summary.json keeps totals only (it must not grow with the runs)."""
    from symkf.scenarios import results
    series = results.load(short_campaign)
    assert series.comparison == "launcher" and series.labels("case") == ["20Hz small", "20Hz large", "10Hz small", "10Hz large"]
    assert series.variables["rms"].dims == ("case", "estimate", "step", "state")
    assert series.variables["time"].attrs["units"] == "s" and series.labels("state_units")[0] == "m/s"
    assert series["steps"].tolist() == [1201, 1201, 601, 601]
    assert series["run_outcome"].shape == (4, 4, 3) and set(series["run_outcome"].ravel()) <= {0, 1, 2}
    summary = json.loads((short_campaign / "summary.json").read_text())
    whole = series["rms_whole_flight"][0, 1, 0]                 # 20Hz small, UKF, V
    assert whole == pytest.approx(summary["cases"]["20Hz small"]["ukf"]["rms_eq11"]["V"], rel=1e-15)
    # eq (11) is the mean over time of RMS(t): the saved RMS(t) gives it back
    assert np.mean(series["rms"][0, 1, :1201, 0]) == pytest.approx(whole, rel=1e-12)

    def lists(node):
        if isinstance(node, dict):
            return [x for v in node.values() for x in lists(v)]
        return [node] if isinstance(node, list) else []
    assert all(len(x) < 3 or len(x) in (6, 24) for x in lists(summary))    # bands, six states, Q: no per-run list


def test_claims_are_sentences_with_their_numbers(short_campaign):
    summary = json.loads((short_campaign / "summary.json").read_text())
    claims = summary["claims"]
    assert {"gap_larger_for_large_error_20Hz", "gap_larger_at_10Hz_small", "rts_le_filter_every_cell"} <= set(claims)
    for rate in (20, 10):
        gap = claims[f"gap_larger_for_large_error_{rate}Hz"]
        assert gap["says"].startswith(f"at {rate} Hz the EKF/UKF gap is larger")
        large, small = (float(gap["compared"].split(f"{rate}Hz {init} ")[1].split()[0]) for init in ("large", "small"))
        ratios = summary["ekf_over_ukf_ratio"]                  # per state, rounded to 3 decimals
        assert large == pytest.approx(np.median(list(ratios[f"{rate}Hz large"].values())), abs=2e-3)
        assert gap["holds"] == (large > 1.05 * small)


def test_the_table_says_how_the_library_computes():
    """The table's first line says whether its runs are the flight bundle's numbers bit for bit."""
    assert C.Campaign(1, 5, exact=True).arithmetic().startswith("every run the flight bundle's numbers bit for bit")
    if lockstep.uses_vector_math(make_config("launcher", **C.LOCKSTEP_BUILD), "ukf"):     # glibc's libmvec here
        assert C.Campaign(1, 5).arithmetic().startswith("EKF and UKF runs in lockstep with libmvec")
        assert C.Campaign(1, 5, preset="paper-like").arithmetic().startswith("EKF runs in lockstep with libmvec")

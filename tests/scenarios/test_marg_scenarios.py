"""``symkf compare marg`` on real recordings: summary.json content and the paper's Fig 3 claim.

Skipped with a reason saying where to get the recordings when they are absent (BROAD:
https://github.com/dlaidig/broad; x-io: https://github.com/xioTechnologies/Fusion).
"""
import json

import numpy as np
import pytest

from symkf.scenarios.marg.data import WHERE_BROAD, WHERE_XIO, data_dir
from symkf.scenarios import cli
from symkf.scenarios.marg.compare import oscillation

BROAD_TRIAL = data_dir() / "broad" / "01_undisturbed_slow_rotation_A.mat"
XIO_CSV = data_dir() / "fusion_sensor_data.csv"


@pytest.mark.skipif(not BROAD_TRIAL.exists(),
                    reason=f"BROAD recording {BROAD_TRIAL} is absent; {WHERE_BROAD}")
def test_compare_on_broad_writes_summary_and_shows_oscillation_growing_with_beta(tmp_path):
    assert cli.main(["compare", "marg", "--data", str(BROAD_TRIAL), "--beta", "0.01,0.5",
                     "--out", str(tmp_path), "--no-plots"]) == 0
    summary = json.loads((tmp_path / "summary.json").read_text())
    low, high = summary["per_beta"]
    assert (low["beta"], high["beta"]) == (0.01, 0.5)
    for entry in (low, high):
        assert set(entry["broad_rmse_deg"]) == {"total", "heading", "inclination", "samples"}
        assert 0.5 < entry["broad_rmse_deg"]["total"] < 10
        assert entry["failed_steps"] == 0
    # the paper's claim: more high-frequency oscillation with larger beta (measured: x2 above 5 Hz,
    # x30 in the first difference while the sensor is still)
    hf_low, hf_high = np.array(low["oscillation"]["hf_rms_deg"]), np.array(high["oscillation"]["hf_rms_deg"])
    assert np.all(hf_high > 1.5 * hf_low)
    still_low = np.array(low["oscillation"]["still_diff_rms_deg"])
    still_high = np.array(high["oscillation"]["still_diff_rms_deg"])
    assert np.all(still_high > 10 * still_low)
    assert high["oscillation"]["error_hf_rms_deg"] > 1.5 * low["oscillation"]["error_hf_rms_deg"]


@pytest.mark.skipif(not XIO_CSV.exists(), reason=f"x-io recording {XIO_CSV} is absent; {WHERE_XIO}")
def test_compare_on_xio_without_reference(tmp_path):
    assert cli.main(["compare", "marg", "--data", str(XIO_CSV), "--beta", "0.01,0.5", "--out", str(tmp_path),
                     "--no-plots"]) == 0
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert "reference_oscillation" not in summary
    low, high = summary["per_beta"]
    assert "broad_rmse_deg" not in low
    assert np.all(np.array(high["oscillation"]["diff_rms_deg"]) > np.array(low["oscillation"]["diff_rms_deg"]))


def test_oscillation_measure_separates_frequencies():
    rate, n = 100.0, 4000
    t = np.arange(n) / rate
    slow = np.radians(20) * np.sin(2 * np.pi * 0.5 * t)
    fast = np.radians(1) * np.sin(2 * np.pi * 20 * t)
    angles = np.column_stack([slow, slow + fast, np.zeros(n)])
    result = oscillation(angles, rate, cutoff_hz=5.0, still=np.ones(n, dtype=bool))
    # leakage of the 20 deg, 0.5 Hz motion past the cutoff stays below 0.1 % of its amplitude
    np.testing.assert_allclose(result["hf_rms_deg"], [0, 1 / np.sqrt(2), 0], atol=0.02)
    assert result["diff_rms_deg"][1] > result["diff_rms_deg"][0]


def _synthetic_xio_csv(path, seconds=20.0, rate=100.0):
    """A still sensor in the x-io CSV layout: time (s), gyro (deg/s), accelerometer (g), magnetometer (uT)."""
    rng = np.random.default_rng(4)
    n = int(seconds * rate)
    rows = np.column_stack([np.arange(n) / rate, rng.normal(0, 0.2, (n, 3)),
                            np.array([0.0, 0.0, 1.0]) + rng.normal(0, 0.01, (n, 3)),
                            np.array([20.0, 0.0, -40.0]) + rng.normal(0, 0.5, (n, 3))])
    header = "Time (s),Gyroscope X (deg/s),Gyroscope Y (deg/s),Gyroscope Z (deg/s),Accelerometer X (g)," \
             "Accelerometer Y (g),Accelerometer Z (g),Magnetometer X (uT),Magnetometer Y (uT),Magnetometer Z (uT)"
    np.savetxt(path, rows, delimiter=",", header=header, comments="")
    return path


def test_symkf_plot_redraws_the_marg_figures_from_the_series_alone(tmp_path, monkeypatch):
    """The Euler angles per beta and sample go to the series file; `symkf plot` draws the same PNGs
    from it without running a filter."""
    from symkf.scenarios import results
    from symkf.scenarios.marg import compare
    data = _synthetic_xio_csv(tmp_path / "still.csv")
    out = tmp_path / "out"
    assert cli.main(["compare", "marg", "--data", str(data), "--beta", "0.01,0.5", "--out", str(out)]) == 0
    saved = results.load(out)
    assert saved.comparison == "marg" and saved["euler"].shape == (2, 2000, 3)
    assert saved.variables["euler"].attrs["units"] == "rad" and saved["beta"].tolist() == [0.01, 0.5]
    summary = json.loads((out / "summary.json").read_text())
    deg = np.degrees(np.unwrap(saved["euler"][1], axis=0))             # the summary's oscillation, from the series
    assert np.sqrt(np.mean(np.diff(deg, axis=0) ** 2, axis=0)).tolist() == pytest.approx(
        summary["per_beta"][1]["oscillation"]["diff_rms_deg"], rel=1e-9)
    monkeypatch.setattr(compare, "run_recording", lambda *a, **k: pytest.fail("symkf plot ran a filter"))
    assert cli.main(["plot", str(out), "--out", str(tmp_path / "again")]) == 0
    for figure in summary["figures"]:
        name = figure.rsplit("/", 1)[-1]
        assert (tmp_path / "again" / name).read_bytes() == (out / name).read_bytes(), name
    assert len(summary["figures"]) == 2

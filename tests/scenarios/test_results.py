"""The saved series of a comparison (scenarios/results.py): netCDF with dimensions and units when
the `results` extra is installed, else .npz with the same content, said once on stderr; loaded back
to the same numbers either way."""
import sys

import numpy as np
import pytest

from symkf.scenarios import results as R


def _series() -> R.Series:
    times, steps = R.padded([np.arange(5) * 0.1, np.arange(3) * 0.2])
    return R.Series("demo", {
        "case": R.var(["case"], ["fast", "slow"]),
        "steps": R.var(["case"], steps, "1"),
        "time": R.var(["case", "step"], times, "s", "time"),
        "rms": R.var(["case", "step"], np.sqrt(times + 1.0), "m", "RMS error"),
        "ok": R.var(["case"], [True, False], "1"),
    }, {"config": "two cases", "runs": 3, "tuning": {"q": [1.0, 2.0]}})


def _check(loaded: R.Series) -> None:
    assert loaded.comparison == "demo" and loaded.labels("case") == ["fast", "slow"]
    assert loaded.variables["time"].dims == ("case", "step") and loaded.variables["rms"].attrs["units"] == "m"
    np.testing.assert_array_equal(R.trimmed(loaded["time"][1], loaded["steps"][1]), np.arange(3) * 0.2)
    assert np.isnan(loaded["time"][1, 3:]).all()
    assert loaded["rms"][0, 4] == np.sqrt(1.4) and loaded["ok"].tolist() == [True, False]
    assert R.attribute(loaded, "runs") == 3 and R.attribute(loaded, "tuning") == {"q": [1.0, 2.0]}


def test_netcdf_round_trip_is_exact_and_self_describing(tmp_path, monkeypatch):
    xr = pytest.importorskip("xarray", reason="netCDF needs xarray and h5netcdf (pip install 'symkf[results]', or -e '.[test]')")
    pytest.importorskip("h5netcdf", reason="netCDF needs xarray and h5netcdf (pip install 'symkf[results]', or -e '.[test]')")
    path = R.save(_series(), tmp_path)
    assert path.name == "series.nc"
    with xr.open_dataset(path) as data:                     # any netCDF reader: names, dims, units
        assert data["rms"].dims == ("case", "step") and data["rms"].attrs["units"] == "m"
        assert data.attrs["comparison"] == "demo"
    _check(R.load(tmp_path))
    loaded = R.load(tmp_path)
    monkeypatch.setattr(R, "netcdf_available", lambda: False)       # read back from netCDF, then saved as .npz
    R.save(loaded, tmp_path / "again")
    _check(R.load(tmp_path / "again"))


def test_without_the_extra_npz_is_written_and_stderr_says_once_how_to_get_netcdf(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(R, "netcdf_available", lambda: False)
    monkeypatch.setattr(R, "_said_fallback", False)
    assert R.save(_series(), tmp_path / "a").name == "series.npz"
    R.save(_series(), tmp_path / "b")
    err = capsys.readouterr().err
    assert err.count("pip install 'symkf[results]'") == 1
    _check(R.load(tmp_path / "a"))


def test_a_folder_without_series_is_refused_by_name(tmp_path):
    with pytest.raises(FileNotFoundError, match="no saved series"):
        R.load(tmp_path)
    np.savez(tmp_path / "series.npz", labels=np.array(["20Hz small"]))        # an older layout, no dims/units
    with pytest.raises(FileNotFoundError, match="earlier symkf.*run the comparison again"):
        R.load(tmp_path)
    with pytest.raises(ValueError, match="dimensions"):
        R.var(["a"], np.zeros((2, 2)))


@pytest.mark.parametrize("missing", ["xarray", "h5netcdf", "h5py"])
def test_netcdf_needs_all_three_packages_of_the_extra(monkeypatch, missing):
    """h5netcdf installs without h5py and then cannot write: each missing package means .npz."""
    monkeypatch.setitem(sys.modules, missing, None)           # `import missing` raises ImportError
    assert R.netcdf_available() is False

"""The launcher figures are drawn for a report: the EKF on top of the UKF, the paper's Table 3 values
beside ours, event lines and the NEES band keyed in one legend outside the panels, and a title naming
the filter configuration and seed (checked on the figure objects before they are saved)."""
import pytest

from symkf.models import launcher as L
from symkf.scenarios.cli import main
from symkf.scenarios.launcher import figures


@pytest.fixture(scope="module")
def drawn(tmp_path_factory, launcher_compiled):
    """{file name: (figure, its axes)} of a short `symkf compare launcher` (20 Hz, 2 runs, 140 s: through staging)."""
    out, captured = tmp_path_factory.mktemp("figures"), {}
    finish = figures._finish

    def keep(plt, fig, axes, title, path):
        captured[path.name] = (fig, axes, title)
        finish(plt, fig, axes, title, path)
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(figures, "_finish", keep)
        assert main(["compare", "launcher", "--runs", "2", "--rates", "20", "--duration", "140", "--seed", "7",
                     "--out", str(out), "--quiet"]) == 0
    return captured


def test_every_figure_names_its_configuration_and_keys_its_lines_outside_the_panels(drawn):
    assert set(drawn) == {"fig_velocity_rms.png", "fig_radius_rms.png", "fig_nees.png", "fig_smoother_rms.png"}
    for name, (fig, axes, title) in drawn.items():
        assert "filters 'correct'" in title and "2 Monte Carlo runs" in title and "seed 7" in title, name
        (legend,) = fig.legends
        labels = [text.get_text() for text in legend.get_texts()]
        assert {"EKF", "UKF", "staging / 2nd ignition"} <= set(labels), (name, labels)
        assert all(ax.get_legend() is None for ax in axes.ravel()), name      # no legend over the data


def test_the_ekf_is_drawn_over_the_ukf(drawn):
    for name, (fig, axes, _) in drawn.items():
        for ax in axes.ravel():
            lines = {line.get_label(): line for line in ax.get_lines()}
            assert lines["EKF"].get_zorder() > lines["UKF"].get_zorder(), name
            assert lines["EKF"].get_marker() not in (None, "None", ""), name


def test_the_rms_figures_put_the_papers_table_3_beside_ours(drawn):
    fig, axes, _ = drawn["fig_velocity_rms.png"]
    small = axes[0, 0]
    paper = {line.get_label(): line.get_ydata()[0] for line in small.get_lines() if line.get_label().startswith("paper")}
    assert sorted(paper.values()) == sorted(L.TABLE3[(20, "small")]["V"])
    assert any("whole-flight RMS" in text.get_text() for text in small.texts)


@pytest.mark.parametrize("netcdf", [True, False], ids=["series.nc", "series.npz"])
def test_symkf_plot_redraws_the_saved_figures_without_a_filter(tmp_path, launcher_compiled, capsys, monkeypatch, netcdf):
    """`symkf plot <folder>` redraws the four figures from the series file alone (netCDF with the
    `results` extra, else .npz): the same PNG bytes as the comparison wrote (no filter runs: the
    campaign and the filters' runs are made unavailable first)."""
    from symkf.scenarios import results
    if netcdf:
        pytest.importorskip("xarray", reason="netCDF needs xarray and h5netcdf (pip install 'symkf[results]', or -e '.[test]')")
        pytest.importorskip("h5netcdf", reason="netCDF needs xarray and h5netcdf (pip install 'symkf[results]', or -e '.[test]')")
    else:
        monkeypatch.setattr(results, "netcdf_available", lambda: False)
    out, again = tmp_path / "run", tmp_path / "again"
    assert main(["compare", "launcher", "--runs", "2", "--rates", "20", "--duration", "60", "--seed", "3",
                 "--out", str(out), "--quiet"]) == 0
    assert sorted(p.name for p in out.glob("series.*")) == ["series.nc" if netcdf else "series.npz"]
    from symkf.runtime import filters
    from symkf.scenarios.launcher import campaign
    monkeypatch.setattr(campaign.Campaign, "run", lambda self: pytest.fail("symkf plot ran a campaign"))
    monkeypatch.setattr(campaign, "run_chunk", lambda *a: pytest.fail("symkf plot ran a filter"))
    monkeypatch.setattr(filters.Filter, "run", lambda *a, **k: pytest.fail("symkf plot ran a filter"))
    monkeypatch.setattr(filters.Filter, "run_lockstep", lambda *a, **k: pytest.fail("symkf plot ran a filter"))
    assert main(["plot", str(out), "--out", str(again)]) == 0
    for name in ("fig_velocity_rms.png", "fig_radius_rms.png", "fig_nees.png", "fig_smoother_rms.png"):
        assert (again / name).read_bytes() == (out / name).read_bytes(), name
    capsys.readouterr()
    assert main(["plot", str(tmp_path / "nothing")]) == 1
    assert "no saved series" in capsys.readouterr().err

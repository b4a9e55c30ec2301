"""The example notebook (docs/notebooks/tracker_campaign.ipynb) runs from a clean folder without
an error, draws its figure, and prints the numbers stored in it (the stored outputs are what the
code gives, to the digits shown)."""
import re
from pathlib import Path

import pytest

NOTEBOOK = Path(__file__).resolve().parents[1] / "docs" / "notebooks" / "tracker_campaign.ipynb"


def _stdout(cell) -> str:
    return "".join(o.get("text", "") for o in cell.outputs if o.output_type == "stream" and o.name == "stdout")


def test_the_example_notebook_runs_and_prints_what_it_stores(tmp_path):
    nbformat = pytest.importorskip("nbformat", reason="the notebook test needs nbclient, nbformat and ipykernel (pip install -e '.[test]')")
    nbclient = pytest.importorskip("nbclient", reason="the notebook test needs nbclient, nbformat and ipykernel (pip install -e '.[test]')")
    pytest.importorskip("ipykernel", reason="the notebook test needs nbclient, nbformat and ipykernel (pip install -e '.[test]')")
    stored = nbformat.read(NOTEBOOK, as_version=4)
    run = nbformat.read(NOTEBOOK, as_version=4)
    nbclient.NotebookClient(run, timeout=180, kernel_name="python3",
                            resources={"metadata": {"path": str(tmp_path)}}).execute()     # raises on a cell error
    checked = [(a, b) for a, b in zip(stored.cells, run.cells) if "checked" in a.metadata.get("tags", [])]
    assert len(checked) == 2
    for old, new in checked:
        assert _stdout(new) == _stdout(old) != ""
    numbers = [float(v) for v in re.findall(r"EKF ([\d.]+) m, UKF ([\d.]+) m", _stdout(checked[1][1]))[0]]
    assert 1 < numbers[0] < 20 and abs(numbers[0] - numbers[1]) < 0.01 * numbers[0]     # the filters nearly coincide
    images = [o for cell in run.cells if cell.cell_type == "code" for o in cell.outputs if "image/png" in o.get("data", {})]
    assert len(images) == 1
    assert (tmp_path / "tracker.py").is_file()
    # stored small: text outputs only, no images or execution counts
    assert all(o.output_type == "stream" for cell in stored.cells if cell.cell_type == "code" for o in cell.outputs)

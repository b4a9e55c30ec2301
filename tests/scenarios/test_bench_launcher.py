"""`symkf bench launcher --json` runs every path and reports consistent rows (numbers not asserted
against wall-clock targets: timing lives in the benchmark, not in tests)."""
import json

from symkf.scenarios.cli import main


def test_bench_json_has_every_path(capsys, launcher_compiled):
    assert main(["bench", "launcher", "--json", "--steps", "300", "--reference-steps", "50"]) == 0
    report = json.loads(capsys.readouterr().out)
    paths = {(r["filter"], r["path"]) for r in report["rows"]}
    for family in ("ekf", "ukf"):
        for path in ("numpy_reference", "compiled_step", "c_loop", "compiled_run"):
            assert (family, path) in paths
    assert all(r["us_per_step"] > 0 for r in report["rows"])
    assert report["paper_ms_per_step"] == {"ekf": 2.32, "ukf": 9.22}
    value = {(r["filter"], r["path"]): r["us_per_step"] for r in report["rows"]}
    assert abs(report["ratios"]["ukf"]["compiled_step/c_loop"]
               - value[("ukf", "compiled_step")] / value[("ukf", "c_loop")]) < 1e-9

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
    assert ("ekf", "c_loop_process") in paths
    by_round = report["ratios by round"]
    assert sorted(by_round) == sorted(f"{f} compiled_step/{p}" for f in ("ekf", "ukf") for p in ("c_loop", "c_loop_process"))
    assert all(len(v) == 5 and min(v) > 0 for v in by_round.values())
    # every path timed in the same interleaved rounds, with its thread's CPU time beside its wall
    # time; the two clocks are accounted apart (a median CPU 2 % above the wall was seen on this
    # machine), so only a CPU figure far from the wall time would be a fault of the bench
    assert report["rounds"] == 5
    for row in report["rows"]:
        assert 0 < row["cpu_us_per_step"] <= 1.5 * row["us_per_step"] + 1e-3, row
    load = report["load_average"]
    assert len(load["before"]) == len(load["after"]) == 3 and min(load["before"] + load["after"]) >= 0


def test_c_loop_does_the_work_of_compiled_step(tmp_path, launcher_compiled):
    """The in-process C loop (the ratio's denominator) steps the same record with the same inputs
    as ``compiled_step``: x and P equal bit for bit after 300 steps of each filter."""
    import numpy as np
    from symkf.codegen import build_model
    from symkf.scenarios.launcher import bench

    work = bench.Workload(300)
    loop = bench.CLoop(work, build_model("launcher").directory, tmp_path)
    for family in bench.FILTERS:
        f = launcher_compiled.filter(family, work.x0, work.P0, bench.TUNING["Q"], **bench._options(family))
        for k in range(300):
            i = work.index(k)
            f.step(float(work.base_times[i - 1]), 1.0 / bench.RATE_HZ, work.z[i].copy(), "radar", q=work.q[i].copy())
        loop.batch(family, 0, 300)
        x, P = loop.state[family]
        assert np.array_equal(f.x, x) and np.array_equal(np.ravel(f.P, "F"), P)


def test_step_breakdown_groups_every_function_of_a_step_once():
    """The parts table's rows of a step: each function counted in one row, libm apart."""
    from symkf.scenarios.launcher.bench import step_breakdown
    counts = {"launcher_fn_segment_and_jac": 5000.0, "launcher_fn_fd_and_jac": 150.0, "launcher_fn_h_and_jac_radar": 300.0,
              "launcher_k_ekf_predict": 2000.0, "launcher_k_ekf_update_radar": 3000.0, "__sincos_fma": 2100.0,
              "__ieee754_atan2_fma": 230.0, "launcher_ekf_step_radar": 460.0, "main": 50.0}
    rows = step_breakdown(counts, "launcher", "ekf")
    assert rows == {"step: propagation": 5150.0, "step: h and H": 300.0, "step: predict kernel": 2000.0,
                    "step: update kernel": 3000.0, "step: libm": 2330.0}

"""examples/flight/: main.c runs the launcher EKF over a radar record written by symkf, built from
the freshly generated bundle alone with floating-point traps on; it matches Python to 1e-12."""
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from symkf.runtime import load
from symkf.scenarios.launcher.record import radar_record, write_radar_record

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "flight"


@pytest.mark.skipif(not EXAMPLE.is_dir(), reason="examples/flight/ ships with the source checkout, not the installed package")
def test_flight_example_matches_python(tmp_path):
    compiled = load("launcher", backend="compiled")
    bundle = compiled.backend.library_path.parent
    for name in ("main.c", "Makefile"):
        shutil.copy(EXAMPLE / name, tmp_path / name)
    proc = subprocess.run(["make", "-C", str(tmp_path), f"BUNDLE={bundle}", "flight_trap"], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    record = radar_record(rate_hz=20)                   # the whole flight to insertion, 20 Hz
    path = write_radar_record(tmp_path / "radar.txt", record)
    proc = subprocess.run([str(tmp_path / "flight_trap"), str(path)], capture_output=True, text=True)
    assert proc.returncode == 0, f"exit {proc.returncode} (-8: a floating-point trap): {proc.stderr[-500:]}"
    rows = np.array([[float(v) for v in line.split()] for line in proc.stdout.splitlines()])
    assert rows.shape == (record.times.size, 2 + 6)
    f = compiled.filter("ekf", record.x0, record.P0, record.Q)
    R = np.asarray(f.measurements[record.measurement]["R"]).reshape(record.R.shape, order="F")
    np.testing.assert_array_equal(R, record.R)              # the record's R is the filter's default
    run = f.run(record.times, record.z, record.measurement, q=record.q)
    np.testing.assert_array_equal(rows[:, 1], run.status)
    np.testing.assert_allclose(rows[:, 2:], run.x, rtol=1e-12, atol=0)
    assert "0 refused steps" in proc.stderr


def test_record_command_writes_a_readable_record(tmp_path):
    from symkf.scenarios.launcher.record import main
    assert main(["--out", str(tmp_path / "r.txt"), "--duration", "2"]) == 0
    lines = (tmp_path / "r.txt").read_text().splitlines()
    assert lines[0] == "symkf-radar-record-1 launcher radar_wgs84"
    n, nx, nz, nq = map(int, lines[1].split())
    assert (n, nx, nz) == (41, 6, 3) and len(lines) == 6 + n
    assert len(lines[6].split()) == 2 + nq + 2 * nz

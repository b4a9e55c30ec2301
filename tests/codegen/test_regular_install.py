"""A user's model outside the repository builds and filters with a REGULAR (non-editable) install,
and its build goes to the per-user cache: a planted ``./build`` in the current directory is ignored."""
import json
import os
import subprocess
import sys
from pathlib import Path

import casadi
import numpy
import pytest
import scipy

import symkf.codegen

REPO = Path(symkf.codegen.__file__).resolve().parents[1]

SCRIPT = """
import json, sys
import numpy as np
import symkf.codegen
from symkf.runtime import load
compiled = load("tracker.py")
ekf = compiled.ekf([0.0, 1.0], np.eye(2), np.diag([0.0, 0.01]))
from symkf.runtime import fastcall
for k in range(3):                       # a list takes the Python path, an array the C fast path
    ekf.step(0.5 * k, 0.5, [0.4 * (k + 1)] if k % 2 else np.array([0.4 * (k + 1)]))
ext = fastcall.extension()
print(json.dumps({"codegen": symkf.codegen.__file__, "library": str(compiled.backend.library_path),
                  "backend": compiled.backend.kind, "x": list(ekf.x),
                  "fastcall": ext and ext.__file__, "fastcall_unavailable": fastcall.unavailable}))
"""


def _regular_install(site: Path) -> None:
    """``pip install --target`` (no editable finder); without the wheel package, the same layout
    copied as pyproject.toml's package-dir maps it."""
    try:
        import wheel  # noqa: F401
    except ImportError:
        import shutil
        import tomllib
        mapping = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["package-dir"]
        for package, folder in mapping.items():
            shutil.copytree(REPO / folder, site / package.replace(".", "/"), ignore=shutil.ignore_patterns("__pycache__"))
        return
    subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--no-build-isolation",
                    "--target", str(site), str(REPO)], check=True, capture_output=True, cwd=site.parent)


@pytest.mark.skipif(not (REPO / "pyproject.toml").is_file(), reason="needs the source checkout")
def test_user_model_with_a_regular_install(tmp_path, write_model):
    site, project, cache = tmp_path / "site", tmp_path / "project", tmp_path / "cache"
    site.mkdir()
    _regular_install(site)
    write_model(project / "tracker.py")
    planted = project / "build" / "tiny"
    planted.mkdir(parents=True)
    (planted / "manifest.json").write_text('{"model": "tiny", "hashed_library": "libtiny.so"}')
    (planted / "libtiny.so").write_bytes(b"planted")
    deps = {str(Path(m.__file__).resolve().parents[1]) for m in (numpy, casadi, scipy)}
    env = {k: v for k, v in os.environ.items() if not k.startswith(("SYMKF_", "PYTHON"))}
    env.update(PYTHONPATH=os.pathsep.join([str(site), *sorted(deps)]), XDG_CACHE_HOME=str(cache))
    # -S: no site-packages processing, so the editable install of this checkout is invisible
    proc = subprocess.run([sys.executable, "-S", "-c", SCRIPT], cwd=project, env=env, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads(proc.stdout.splitlines()[-1])
    assert Path(out["codegen"]).is_relative_to(site)
    assert out["backend"] == "compiled"
    assert Path(out["library"]).parent.parent == cache / "symkf"
    assert Path(out["library"]).parent.name.startswith("tiny@")
    assert numpy.all(numpy.isfinite(out["x"])) and abs(out["x"][0] - 1.2) < 0.3
    # the step fast path (C extension) is compiled at first use into the same per-user cache
    assert out["fastcall"] and Path(out["fastcall"]).is_relative_to(cache / "symkf" / "_fastcall"), out


"""generate -> build -> load: content-hash cache, atomic installs, stale and missing pieces."""
import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

from symkf.codegen import CompilerNotFound, build, build_model, compiler, content_hash, make_config
from symkf.models import launcher as L
from symkf.runtime import StaleLibraryError, load
from symkf.runtime.backends import CompiledBackend


def test_unchanged_build_is_up_to_date(launcher_compiled):
    result = build_model("launcher")
    assert result.up_to_date and result.library.exists()
    manifest = json.loads(result.manifest.read_text())
    assert manifest["content_hash"] == result.content_hash
    assert {k["name"] for k in manifest["kernels"]} >= {"ekf_step_radar", "ukf_step_radar", "jac_fd", "jac_h_radar"}
    assert manifest["kernels"][0]["inputs"][0] == {"name": "t", "shape": [1, 1], "unit": "s",
                                                   "description": "time at the start of the step"}


def test_editing_a_model_changes_the_hash(tmp_path, monkeypatch):
    """Any edit under models/ or codegen/ gives a new content hash, so a stale library never matches."""
    config, cc = make_config("launcher"), compiler()
    before = content_hash("launcher", config, cc)
    edited = tmp_path / "models"
    shutil.copytree(build.MODELS_DIR, edited)
    source = (edited / "launcher.py").read_text()
    (edited / "launcher.py").write_text(source.replace("SCALE_HEIGHT = 7.2e3", "SCALE_HEIGHT = 7.3e3"))
    monkeypatch.setattr(build, "MODELS_DIR", edited)
    assert content_hash("launcher", config, cc) != before
    assert not build.is_up_to_date(build.build_root() / "launcher", "launcher", content_hash("launcher", config, cc))


def test_half_written_build_folder_is_rebuilt(tmp_path, monkeypatch):
    monkeypatch.setenv("SYMKF_BUILD_DIR", str(tmp_path))
    folder = tmp_path / "launcher"
    folder.mkdir()
    (folder / "manifest.json").write_text('{"content_hash": "trunc')          # a crash mid-write
    (tmp_path / ".launcher.tmp-crashed").mkdir()                            # an abandoned staging dir
    result = build_model("launcher")
    assert not result.up_to_date
    backend = CompiledBackend.from_directory(result.directory)
    assert backend.manifest["content_hash"] == result.content_hash


def test_library_with_another_hash_is_refused(launcher_compiled):
    manifest = dict(launcher_compiled.backend.manifest, content_hash="0" * 32)
    with pytest.raises(StaleLibraryError, match="rebuild"):
        CompiledBackend(launcher_compiled.backend.library_path, manifest)


def test_concurrent_builds_both_succeed(tmp_path):
    code = "from symkf.codegen import build_model; print(build_model('launcher').content_hash)"
    env = dict(os.environ, SYMKF_BUILD_DIR=str(tmp_path))
    procs = [subprocess.Popen([sys.executable, "-c", code], env=env, stdout=subprocess.PIPE, text=True)
             for _ in range(2)]
    hashes = [p.communicate(timeout=300)[0].strip() for p in procs]
    assert all(p.returncode == 0 for p in procs) and hashes[0] == hashes[1]
    assert not list(tmp_path.glob(".launcher.tmp-*")) and not list(tmp_path.glob(".launcher.old-*"))
    CompiledBackend.from_directory(tmp_path / "launcher")


def test_missing_compiler_falls_back_to_casadi_vm_with_same_numbers(launcher_compiled, monkeypatch):
    monkeypatch.setenv("CC", "no-such-compiler-symkf")
    with pytest.raises(CompilerNotFound, match="no C compiler found") as info:
        compiler()
    assert "\n" not in str(info.value)
    with pytest.warns(RuntimeWarning, match="virtual machine"):
        vm = load("launcher")
    assert vm.backend.kind == "casadi-vm"
    x0 = L.initial_state() + np.array([5.0, 0, 0, 500.0, 0, 0])
    P0, Q = np.diag([10.0, 1e-4, 1e-4, 1e3, 1e-5, 1e-5]) ** 2, np.diag([1.0, 1e-8, 1e-8, 1.0, 1e-14, 1e-14])
    for family in ("ekf", "ukf"):
        a, b = vm.filter(family, x0, P0, Q), launcher_compiled.filter(family, x0, P0, Q)
        for k in range(5):
            for f in (a, b):
                f.step(0.05 * k, 0.05, [60.0 + 20 * k, 1.2, 2.5], q=L.station_params(1))
        np.testing.assert_allclose(a.x, b.x, rtol=1e-12)
        np.testing.assert_allclose(a.P, b.P, rtol=1e-9, atol=1e-12 * np.abs(b.P).max())

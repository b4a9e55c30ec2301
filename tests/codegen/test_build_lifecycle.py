"""generate -> build -> load: a hash of what is generated, private build roots, verified libraries.

An in-process edit gives new numbers (a fresh process agrees), nothing in the current
directory is ever loaded, a damaged library is rebuilt (never opened), concurrent builds of two
configurations both succeed, killed builds leave no staging folder and no compiler behind.
"""
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from symkf.codegen import BuildError, BundleRepairWarning, CompilerNotFound, build_model, compiler, generated_hash, make_config
from symkf.codegen import build_folders, compiler_pool, hashing
from symkf.codegen.compilation import UnitCompiler
from symkf.codegen.manifest import sha256_file
from symkf.models import ModelError, get_model
from symkf.models import launcher as L
from symkf.runtime import StaleLibraryError, load
from symkf.runtime.backends import CompiledBackend


@pytest.fixture
def private_build(tmp_path, monkeypatch):
    root = tmp_path / "build"
    monkeypatch.setenv("SYMKF_BUILD_DIR", str(root))
    return root


def _filter_numbers(compiled) -> np.ndarray:
    """Three EKF steps of the tiny cart model; the state after them."""
    ekf = compiled.ekf([0.0, 1.0], np.eye(2), np.diag([0.0, 0.01]))
    for k in range(3):
        ekf.step(0.5 * k, 0.5, [0.4 * (k + 1)])
    return np.array(ekf.x)


def test_unchanged_build_is_up_to_date(launcher_compiled):
    result = build_model("launcher")
    assert result.up_to_date and result.library.exists()
    manifest = json.loads(result.manifest.read_text())
    assert manifest["content_hash"] == result.content_hash
    assert manifest["library_sha256"] == sha256_file(result.library)
    assert {k["name"] for k in manifest["kernels"]} >= {"ekf_step_radar", "ukf_step_radar", "jac_fd", "jac_h_radar"}
    assert manifest["kernels"][0]["inputs"][0] == {"name": "t", "shape": [1, 1], "unit": "s",
                                                   "description": "time at the start of the step"}


def test_model_from_a_file_a_module_name_a_module_and_a_model(tmp_path, write_model, monkeypatch):
    path = write_model(tmp_path / "mypkg" / "tracker.py")
    (tmp_path / "mypkg" / "__init__.py").write_text("")
    monkeypatch.syspath_prepend(str(tmp_path))
    import importlib
    module = importlib.import_module("mypkg.tracker")
    names = {get_model(spec).name for spec in (str(path), path, "mypkg.tracker", module, module.build())}
    assert names == {"tiny"}
    with pytest.raises(ModelError, match="no model 'nosuch_model_x'"):
        get_model("nosuch_model_x")
    with pytest.raises(ModelError, match="missing.py"):
        get_model(str(tmp_path / "missing.py"))


def test_in_process_edit_gives_new_numbers_and_a_fresh_process_agrees(tmp_path, write_model, private_build):
    path = write_model(tmp_path / "tracker.py", drag=0.1)
    before = _filter_numbers(load(str(path)))
    write_model(path, drag=0.5)                       # same size, same second: no bytecode cache, no mtime
    after = _filter_numbers(load(str(path)))
    assert not np.allclose(before, after)
    script = ("import sys, numpy as np; from symkf.runtime import load; m = load(sys.argv[1]); "
              "e = m.ekf([0.0, 1.0], np.eye(2), np.diag([0.0, 0.01]))\n"
              "for k in range(3): e.step(0.5 * k, 0.5, [0.4 * (k + 1)])\n"
              "print(repr(list(e.x)))")
    for root in (private_build, tmp_path / "clean"):     # the same build folder, then a clean build
        env = dict(os.environ, SYMKF_BUILD_DIR=str(root))
        out = subprocess.run([sys.executable, "-c", script, str(path)], env=env, capture_output=True,
                             text=True, check=True).stdout
        np.testing.assert_array_equal(eval(out), after)


def test_hash_is_of_what_is_generated(tmp_path, write_model):
    """File times and other models' files do not matter; an equation or an option does."""
    a, b = write_model(tmp_path / "a.py"), write_model(tmp_path / "b.py", name="other")
    config = make_config(str(a))
    key = generated_hash(get_model(str(a)), config)
    os.utime(a, (0, 0))
    write_model(b, drag=0.3, name="other")
    a.write_text(a.read_text() + "\n# a comment\n")
    assert generated_hash(get_model(str(a)), config) == key
    assert generated_hash(get_model(str(a)), make_config(str(a), rk4_substeps=2)) != key
    write_model(a, drag=0.2)
    assert generated_hash(get_model(str(a)), config) != key


def test_planted_library_in_the_current_directory_is_never_loaded(tmp_path, write_model, monkeypatch):
    """A regular install builds into the per-user cache, never ./build."""
    path = write_model(tmp_path / "tracker.py")
    planted = tmp_path / "cwd" / "build" / "tiny"
    planted.mkdir(parents=True)
    (planted / "manifest.json").write_text(json.dumps({"model": "tiny", "content_hash": "x", "library_sha256": "y",
                                                       "hashed_library": "libtiny.so"}))
    (planted / "libtiny.so").write_bytes(b"\x7fELF planted")
    monkeypatch.chdir(tmp_path / "cwd")
    monkeypatch.delenv("SYMKF_BUILD_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.setattr(build_folders, "development_checkout", lambda: None)
    assert build_folders.build_root() == tmp_path / "cache" / "symkf"
    compiled = load(str(path))
    assert Path(compiled.backend.library_path).parent.parent == tmp_path / "cache" / "symkf"
    assert Path(compiled.backend.library_path).parent.name.startswith("tiny@")
    assert (planted / "libtiny.so").read_bytes() == b"\x7fELF planted"


def test_damaged_or_replaced_library_is_rebuilt_never_opened(tmp_path, write_model, private_build, monkeypatch):
    """(A library this process has already mapped cannot be protected from in-place damage, so each
    damaged library here is a fresh build that was never opened.)"""
    path = write_model(tmp_path / "tracker.py")
    monkeypatch.setenv("SYMKF_BUILD_DIR", str(tmp_path / "reference"))
    expected = _filter_numbers(load(str(path)))
    monkeypatch.setenv("SYMKF_BUILD_DIR", str(private_build))
    for damage in (lambda p: p.write_bytes(p.read_bytes()[:1000]),                  # truncated
                   lambda p: p.write_bytes(_flip_byte(p.read_bytes(), 5000))):     # one byte changed
        library = build_model(str(path), force=True).library
        damage(library)
        with pytest.raises(StaleLibraryError, match="SHA-256"):
            CompiledBackend.from_directory(library.parent)
        with pytest.warns(BundleRepairWarning, match="does not match its digest"):
            rebuilt = build_model(str(path))
        assert not rebuilt.up_to_date and rebuilt.library != library
    np.testing.assert_array_equal(_filter_numbers(load(str(path))), expected)
    assert os.stat(rebuilt.library).st_ino != os.stat(rebuilt.directory / "libtiny.so").st_ino


def _flip_byte(data: bytes, i: int) -> bytes:
    return data[:i] + bytes([data[i] ^ 0xFF]) + data[i + 1:]


def test_build_root_writable_by_others_is_refused(tmp_path, write_model, private_build):
    private_build.mkdir(mode=0o777)
    os.chmod(private_build, 0o777)
    with pytest.raises(BuildError, match="writable by other users"):
        build_model(str(write_model(tmp_path / "tracker.py")))


def test_lock_file_symlink_is_refused(tmp_path, write_model, private_build):
    private_build.mkdir()
    model = get_model(str(write_model(tmp_path / "tracker.py")))
    key = hashing.content_hash(model, make_config(model), compiler())
    (private_build / f".tiny@{key[:16]}.lock").symlink_to(tmp_path / "victim")     # the lock of this edit
    with pytest.raises(BuildError, match="symlink"):
        build_model(model)
    assert not (tmp_path / "victim").exists()


def test_stale_staging_folders_are_cleaned_and_half_written_folder_rebuilt(tmp_path, write_model, private_build):
    path = write_model(tmp_path / "tracker.py")
    (private_build / ".tiny.tmp-killed" / "sub").mkdir(parents=True)
    (private_build / ".tiny.old-1-2").mkdir()
    (private_build / "tiny").mkdir()
    (private_build / "tiny" / "manifest.json").write_text('{"content_hash": "trunc')     # a crash mid-write
    result = build_model(str(path))
    assert not result.up_to_date
    assert sorted(p.name for p in private_build.iterdir()) == [".objects", f".{result.directory.name}.lock", "tiny",
                                                                result.directory.name]
    assert (private_build / "tiny").resolve() == result.directory           # build/tiny: the build made last


def test_concurrent_builds_of_two_configurations_both_succeed(tmp_path, write_model, private_build):
    path = write_model(tmp_path / "tracker.py")
    code = ("import sys; from symkf.codegen import build_model; "
            "r = build_model(sys.argv[1], rk4_substeps=int(sys.argv[2])); print(r.directory.name)")
    procs = [subprocess.Popen([sys.executable, "-c", code, str(path), str(n)], stdout=subprocess.PIPE, text=True)
             for n in (1, 2)]
    folders = [p.communicate(timeout=300)[0].strip() for p in procs]
    assert all(p.returncode == 0 for p in procs)
    assert folders[0].startswith("tiny@") and folders[1].startswith("tiny-") and len(folders[1]) == len("tiny-@") + 24
    for n in (1, 2, 1):                                  # switching options back and forth: no rebuild
        assert build_model(str(path), rk4_substeps=n).up_to_date
    assert not list(private_build.glob(".*.tmp-*")) and not list(private_build.glob(".*.old-*"))


@pytest.mark.parametrize("started_by", ["setpriv", "preexec_fn"])
def test_killed_build_leaves_no_compiler_running(tmp_path, private_build, started_by):
    """The guard shell learns of the build's death by PR_SET_PDEATHSIG, set by util-linux's
    setpriv where it has --pdeathsig (the compiler then starts by vfork), else in the child."""
    if started_by == "setpriv" and not compiler_pool._pdeathsig_wrapper():
        pytest.skip("util-linux's setpriv with --pdeathsig is not on this machine (the preexec_fn case runs instead)")
    fallback = "compiler_pool._pdeathsig_wrapper = lambda: (); " if started_by == "preexec_fn" else ""
    code = f"from symkf.codegen import build_model, compiler_pool; {fallback}build_model('launcher', rk4_substeps=3)"
    proc = subprocess.Popen([sys.executable, "-c", code])
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and not _processes_inside(private_build):
        time.sleep(0.05)
    assert _processes_inside(private_build), "the compiler never started"
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline and _processes_inside(private_build):
        time.sleep(0.05)
    assert not _processes_inside(private_build)


def _processes_inside(folder: Path) -> list[int]:
    """Processes whose working directory is inside ``folder`` (the compiler runs in the staging folder)."""
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                if str(Path(os.readlink(entry / "cwd"))).startswith(str(folder)):
                    found.append(int(entry.name))
            except OSError:
                pass
    return found


def test_no_compiler_still_loads_an_up_to_date_library(tmp_path, write_model, private_build, monkeypatch):
    path = write_model(tmp_path / "tracker.py")
    expected = _filter_numbers(load(str(path)))
    monkeypatch.setenv("CC", "no-such-compiler-symkf")
    compiled = load(str(path))
    assert compiled.backend.kind == "compiled"
    np.testing.assert_array_equal(_filter_numbers(compiled), expected)


def test_export_bundle_anywhere(tmp_path, write_model, private_build):
    from symkf.scenarios.cli import main
    out = tmp_path / "flight"
    assert main(["build", str(write_model(tmp_path / "tracker.py")), "--out", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["Makefile", "libtiny.so", "manifest.json", "tiny.h", "tiny_api.c",
                                                     "tiny_fn_fd.c", "tiny_fn_fd_and_jac.c", "tiny_fn_h_and_jac_gps.c",
                                                     "tiny_fn_h_gps.c", "tiny_fn_jac_fd.c", "tiny_fn_jac_h_gps.c",
                                                     "tiny_hash.c", "tiny_k_ekf_predict.c", "tiny_k_ekf_smooth.c", "tiny_k_ekf_step_gps.c",
                                                     "tiny_k_ekf_update_gps.c", "tiny_k_f.c", "tiny_k_fd.c",
                                                     "tiny_k_h_gps.c", "tiny_k_jac_fd.c", "tiny_k_jac_h_gps.c"]
    proc = subprocess.run(["make", "-j2", "-C", str(out), "all"], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-2000:]          # the exported units build alone


@pytest.mark.parametrize("option, message", [("precision=half", "precision: expected one of"),
                                             ("rk4_substeps=0", "rk4_substeps: expected an integer >= 1"),
                                             ("rk4_subteps=2", "unknown codegen option(s) ['rk4_subteps']"),
                                             ("optimization=fast", "optimization: expected compiler flags"),
                                             ('unit_optimization={"*_k_f.c": "fast"}', "unit_optimization: expected")])
def test_bad_or_misspelt_codegen_option_is_one_line_and_builds_nothing(tmp_path, write_model, private_build,
                                                                         capsys, option, message):
    from symkf.scenarios.cli import main
    assert main(["build", str(write_model(tmp_path / "tracker.py")), "--set", option]) == 1
    err = capsys.readouterr().err
    assert err.startswith("symkf build: ") and message in err and err.count("\n") == 1
    assert not private_build.exists() or not any(private_build.iterdir())


def test_missing_compiler_falls_back_to_casadi_vm_with_same_numbers(launcher_compiled, tmp_path, monkeypatch):
    monkeypatch.setenv("SYMKF_BUILD_DIR", str(tmp_path / "empty"))
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
                f.step(0.05 * k, 0.05, [60.0 + 20 * k, 1.2, 2.5], "radar", q=L.station_params(1))
        np.testing.assert_allclose(a.x, b.x, rtol=1e-12)
        np.testing.assert_allclose(a.P, b.P, rtol=1e-9, atol=1e-12 * np.abs(b.P).max())


def test_library_with_another_hash_is_refused(launcher_compiled):
    manifest = dict(launcher_compiled.backend.manifest, content_hash="0" * 32)
    with pytest.raises(StaleLibraryError, match="rebuild"):
        CompiledBackend(launcher_compiled.backend.library_path, manifest)


def test_an_edit_recompiles_only_the_functions_whose_code_changed(tmp_path, write_model, private_build):
    """One unit per function (each kernel and each function the kernels call), objects cached by
    their text: a dynamics edit recompiles the functions that evaluate f, a measurement edit those
    that evaluate h; the filter kernels, which call them, and the API unit are reused."""
    path = write_model(tmp_path / "tracker.py", drag=0.1)
    cold = build_model(str(path))
    assert len(cold.compiled) == len(json.loads(cold.manifest.read_text())["sources"])
    write_model(path, drag=0.2)
    edited = build_model(str(path))
    assert sorted(edited.compiled) == ["tiny_fn_fd.c", "tiny_fn_fd_and_jac.c", "tiny_hash.c", "tiny_k_f.c"]
    predict = (edited.directory / "tiny_k_ekf_predict.c").read_text()
    assert "SYMKF_INTERNAL int tiny_fn_fd_and_jac(" in predict and "/* in tiny_fn_fd_and_jac.c */" in predict
    step = (edited.directory / "tiny_k_ekf_step_gps.c").read_text()
    assert "SYMKF_INTERNAL int tiny_k_ekf_predict(" in step                          # declared, not copied:
    assert re.findall(r"^SYMKF_INTERNAL int (\w+)\(.*\{$", step, flags=re.M) == ["tiny_k_ekf_step_gps"]
    path.write_text(path.read_text().replace('"measured position", pos)', '"measured position", 1.5 * pos)'))
    measured = build_model(str(path))                      # a new term in h: h's functions, work sizes
    assert not {"tiny_fn_fd.c", "tiny_fn_fd_and_jac.c", "tiny_k_f.c", "tiny_k_ekf_predict.c"} & set(measured.compiled)
    path.write_text(path.read_text().replace("1.5 * pos", "2.5 * pos"))
    measured = build_model(str(path))                      # a constant of h: h's functions only
    assert sorted(measured.compiled) == ["tiny_fn_h_and_jac_gps.c", "tiny_fn_h_gps.c", "tiny_hash.c"]
    write_model(path, drag=0.1)                                                          # back: all from the cache
    assert build_model(str(path)).compiled == ()


def test_units_matching_a_pattern_get_their_own_optimization_and_the_same_numbers(tmp_path, write_model,
                                                                                    private_build):
    path = write_model(tmp_path / "tracker.py")
    faster = load(str(path), unit_optimization={"*_k_ekf_step_*": "-O2 -fno-math-errno"})
    manifest = json.loads(faster.build.manifest.read_text())
    assert manifest["unit_optimization"] == {"tiny_k_ekf_step_gps.c": "-O2 -fno-math-errno"}
    makefile = (faster.build.directory / "Makefile").read_text()
    assert "\t$(CC) $(CFLAGS) -O2 -fno-math-errno -fPIC -c -o $@ tiny_k_ekf_step_gps.c" in makefile
    assert "\t$(CC) $(CFLAGS) -fPIC -c -o $@ tiny_k_ekf_predict.c" in makefile
    assert faster.build.directory.name.startswith("tiny-")                  # a configuration of its own
    np.testing.assert_array_equal(_filter_numbers(faster), _filter_numbers(load(str(path))))


def test_a_unit_rewritten_while_it_compiles_is_linked_from_its_final_text(private_build):
    """Units compile as soon as they are written (the model's own functions before the filter
    families exist): one written again with other text is restarted, one the final code does not
    have is removed, and the object linked is the final text's."""
    folder = private_build / "staging"
    folder.mkdir(parents=True)
    unit = "int value_{0}(void);\nint value_{0}(void) {{ return {1}; }}\n"
    with UnitCompiler(folder, compiler(), make_config("launcher"), "none.h") as units:
        units.add({"a.c": unit.format("a", 1), "b.c": unit.format("b", 2)})
        units.add({"a.c": unit.format("a", 3)})
        objects, compiled = units.finish(["a.c"])
    assert compiled == ["a.c"] and objects == [folder / "a.o"]
    assert sorted(p.name for p in folder.iterdir() if not p.name.startswith("a.")) == []
    assert subprocess.run(compiler().split() + ["-shared", "-o", "liba.so", "a.o"], cwd=folder).returncode == 0
    import ctypes
    assert ctypes.CDLL(str(folder / "liba.so")).value_a() == 3


def test_damaged_cached_object_is_recompiled_never_linked(tmp_path, write_model, private_build):
    path = write_model(tmp_path / "tracker.py")
    expected = _filter_numbers(load(str(path)))
    for obj in (private_build / ".objects").glob("*.o"):
        obj.write_bytes(_flip_byte(obj.read_bytes(), 100))                # every cached object damaged
    rebuilt = build_model(str(path), force=True)
    assert len(rebuilt.compiled) == len(json.loads(rebuilt.manifest.read_text())["sources"])
    np.testing.assert_array_equal(_filter_numbers(load(str(path))), expected)
    assert build_model(str(path), force=True).compiled == ()             # the cache was repaired


def test_header_constants_come_from_the_file_built_not_the_package(tmp_path, write_model, private_build):
    """A user's file named like a paper model gets its own constants in the header, and an edited
    constant reaches the header (constants are part of what is hashed)."""
    path = write_model(tmp_path / "launcher.py", drag=0.1, name="launcher")
    first = build_model(str(path))
    header = (first.directory / "launcher.h").read_text()
    assert "#define LAUNCHER_DRAG 0.1" in header and "LAUNCHER_MU_EARTH" not in header
    write_model(path, drag=0.25, name="launcher")
    second = build_model(str(path))
    assert second.content_hash != first.content_hash
    assert "#define LAUNCHER_DRAG 0.25" in (second.directory / "launcher.h").read_text()


def test_every_codegen_module_is_hashed_and_an_edit_of_one_changes_the_hash(tmp_path, write_model, monkeypatch):
    """The content hash covers the source of every codegen module but the families (those a
    model asks for are added per model): a comment edited in any of them invalidates the cache."""
    codegen = Path(hashing.__file__).parent
    files = {".".join(("symkf.codegen",) + p.relative_to(codegen).with_suffix("").parts)
             for p in codegen.rglob("*.py") if p.name != "__init__.py" and "families" not in p.parts}
    assert files <= set(hashing.FRAMEWORK_MODULES)
    model = get_model(str(write_model(tmp_path / "tracker.py")))
    config = make_config(model)
    before = hashing.generated_hash(model, config)
    for name in ("symkf.codegen.lifecycle", "symkf.codegen.manifest", "symkf.codegen.compiler_pool"):
        module = sys.modules[name]
        edited = tmp_path / f"{name}.py"
        edited.write_text(Path(module.__file__).read_text() + "# an edited comment\n")
        with monkeypatch.context() as patch:
            patch.setattr(module, "__file__", str(edited))
            assert hashing.generated_hash(model, config) != before, name
    assert hashing.generated_hash(model, config) == before


def test_a_load_reads_the_manifest_once_and_hashes_each_file_once(launcher_compiled, monkeypatch):
    """The check hashes each bundle file and the library once; the load hashes the library once
    more, from the descriptor it is then opened by (not counted here: not through sha256_file)."""
    from symkf.codegen import manifest
    calls = {"read": 0, "hash": 0}

    def counted(function, key):
        def call(*args):
            calls[key] += 1
            return function(*args)
        return call
    monkeypatch.setattr(manifest, "read_manifest", counted(manifest.read_manifest, "read"))
    monkeypatch.setattr(manifest, "sha256_file", counted(manifest.sha256_file, "hash"))
    compiled = load("launcher")
    assert compiled.build.up_to_date
    assert calls == {"read": 1, "hash": len(compiled.backend.manifest["files"]) + 1}


def test_the_vm_backend_validates_the_model_once(tmp_path, write_model, monkeypatch):
    from symkf.models.base import Model
    validated = []
    original = Model.validate
    monkeypatch.setattr(Model, "validate", lambda self: validated.append(self.name) or original(self))
    assert load(str(write_model(tmp_path / "tracker.py")), backend="casadi-vm").backend.kind == "casadi-vm"
    assert validated == ["tiny"]


def test_an_edit_of_a_c_template_changes_the_hash(tmp_path, write_model, monkeypatch):
    """The static C and Make text lives in template files, not modules: the hash covers them too."""
    import shutil
    from symkf.codegen.c_backend import template_util
    model = get_model(str(write_model(tmp_path / "tracker.py")))
    config = make_config(model)
    before = hashing.generated_hash(model, config)
    copy = tmp_path / "backend"
    shutil.copytree(Path(template_util.__file__).parent / "templates", copy / "templates")
    (copy / "templates" / "finite.c").write_text((copy / "templates" / "finite.c").read_text() + "/* edited */\n")
    monkeypatch.setattr(template_util.resources, "files", lambda package: copy)
    template_util.templates_digest.cache_clear()
    try:
        assert hashing.generated_hash(model, config) != before
    finally:
        monkeypatch.undo()
        template_util.templates_digest.cache_clear()
    assert hashing.generated_hash(model, config) == before

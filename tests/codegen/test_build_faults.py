"""Faults as messages: a disk that fills during a build, a read-only build folder with a stale
library, a model file that raises: one line saying what happened and what to do, no traceback,
no temporary left. The disk and the read-only folder are real (a small tmpfs, mounted as root;
skipped otherwise) and also simulated (ENOSPC from the write itself)."""
import errno
import os
import subprocess
import sys

import pytest

from symkf.codegen import BuildError, build_model
from symkf.codegen import safe_files
from symkf.models import ModelError, get_model
from symkf.scenarios.cli import main


def _mount(folder, size: str) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    proc = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(folder)], capture_output=True)
    if proc.returncode != 0:
        pytest.skip(f"needs root to mount a small tmpfs as a full disk ({proc.stderr.decode().strip() or 'not root'})")


@pytest.fixture
def small_disk(tmp_path):
    """``mount(size)``: a tmpfs of that size at tmp_path / "disk" (unmounted after the test)."""
    folder = tmp_path / "disk"
    mounted = []

    def mount(size: str):
        _mount(folder, size)
        mounted.append(folder)
        return folder
    yield mount
    for folder in mounted:
        subprocess.run(["umount", "-l", str(folder)], capture_output=True)


def _temporaries(folder) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*")
                  if p.name.endswith(".tmp") or ".tmp-" in p.name or ".old-" in p.name or ".link-" in p.name)


def _cli(args, capsys) -> tuple[int, str]:
    """The return code and stderr without the build's progress lines (codegen/progress.py)."""
    code = main(args)
    lines = capsys.readouterr().err.splitlines(keepends=True)
    return code, "".join(line for line in lines if not line.startswith(("symkf: building ", "symkf: built ")))


@pytest.mark.parametrize("size", ["256k", "1m"])
def test_a_disk_that_fills_during_a_build_is_one_line_and_leaks_nothing(tmp_path, write_model, small_disk,
                                                                         monkeypatch, capsys, size):
    disk = small_disk(size)
    monkeypatch.setenv("SYMKF_BUILD_DIR", str(disk / "build"))
    code, err = _cli(["build", str(write_model(tmp_path / "tracker.py"))], capsys)
    if code == 0:                                          # it fitted: then it must be whole
        assert build_model(str(tmp_path / "tracker.py")).up_to_date
    else:
        assert err.count("\n") == 1 and "disk is full" in err and "SYMKF_BUILD_DIR" in err, err
        assert "Traceback" not in err
    assert _temporaries(disk) == []


def test_enospc_while_writing_the_bundle_is_one_line_and_leaks_nothing(tmp_path, write_model, monkeypatch, capsys):
    root = tmp_path / "build"
    monkeypatch.setenv("SYMKF_BUILD_DIR", str(root))
    original = type(tmp_path).write_text

    def full(self, *args, **kwargs):
        if self.name == "tiny.h":
            raise OSError(errno.ENOSPC, "No space left on device", str(self))
        return original(self, *args, **kwargs)
    monkeypatch.setattr(type(tmp_path), "write_text", full)
    code, err = _cli(["build", str(write_model(tmp_path / "tracker.py"))], capsys)
    assert code == 1 and err.count("\n") == 1 and "the disk of" in err and "is full" in err and "tiny.h" in err
    assert _temporaries(root) == [] and not list(root.glob("tiny*"))


def test_enospc_in_an_exclusive_write_removes_the_temporary(tmp_path, monkeypatch):
    calls = []

    def short_write(fd, data):
        calls.append(fd)
        raise OSError(errno.ENOSPC, "No space left on device")
    monkeypatch.setattr(safe_files.os, "write", short_write)
    with pytest.raises(OSError, match="No space left"):
        safe_files.write_exclusive(tmp_path / "record", b"x" * 100)
    monkeypatch.undo()
    assert calls and list(tmp_path.iterdir()) == []


def test_a_read_only_folder_with_a_stale_library_is_one_line(tmp_path, write_model, small_disk, monkeypatch, capsys):
    disk = small_disk("8m")
    monkeypatch.setenv("SYMKF_BUILD_DIR", str(disk / "build"))
    path = write_model(tmp_path / "tracker.py")
    result = build_model(str(path))
    result.library.write_bytes(result.library.read_bytes()[:1000])          # stale
    subprocess.run(["mount", "-o", "remount,ro", str(disk)], check=True)
    code, err = _cli(["build", str(path)], capsys)
    assert code == 1 and err.count("\n") == 1 and "is read-only" in err and "SYMKF_BUILD_DIR" in err, err
    with pytest.raises(BuildError, match="is read-only"):
        build_model(str(path))


def test_an_up_to_date_build_on_a_read_only_folder_still_loads(tmp_path, write_model, small_disk, monkeypatch):
    disk = small_disk("8m")
    monkeypatch.setenv("SYMKF_BUILD_DIR", str(disk / "build"))
    path = write_model(tmp_path / "tracker.py")
    build_model(str(path))
    subprocess.run(["mount", "-o", "remount,ro", str(disk)], check=True)
    from symkf.runtime import load
    assert load(str(path)).build.up_to_date


@pytest.mark.parametrize("text, message", [
    ("import casadi\nX = 1 / 0\n", "line 2 raised ZeroDivisionError executing it: division by zero"),
    ("def build():\n    return undefined_name\n", "line 2 raised NameError in build(): name 'undefined_name'"),
    ("import no_such_module_symkf\n", "line 1 raised ModuleNotFoundError executing it"),
    ("def build(:\n", "line 1: invalid syntax")])
def test_a_model_file_that_raises_is_one_line(tmp_path, capsys, text, message):
    path = tmp_path / "broken.py"
    path.write_text(text)
    code, err = _cli(["build", str(path)], capsys)
    assert code == 1 and err.count("\n") == 1 and message in err and str(path) in err and "Traceback" not in err
    with pytest.raises(ModelError, match="fix the"):
        get_model(str(path))


def test_the_cli_of_a_fresh_process_prints_no_traceback(tmp_path):
    path = tmp_path / "broken.py"
    path.write_text("raise RuntimeError('the author broke it')\n")
    proc = subprocess.run([sys.executable, "-m", "symkf.scenarios.cli", "build", str(path)], capture_output=True,
                          text=True, env=dict(os.environ, SYMKF_BUILD_DIR=str(tmp_path / "build")))
    assert proc.returncode == 1 and proc.stderr.count("\n") == 1 and "the author broke it" in proc.stderr

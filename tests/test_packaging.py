"""What a regular install ships: a wheel built from a copy of the sources holds every package folder
(a folder with an ``__init__.py`` under models/, codegen/, runtime/, scenarios/), every module and
every data file read at run time (the ``.c`` sources: the step fast path, the benches' C drivers),
so an experiment that works in the checkout also works installed from the wheel."""
import importlib.util
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
ROOMS = ("models", "codegen", "runtime", "scenarios")
#: Files of a room shipped with the code (package data): everything that is not Python.
DATA_SUFFIXES = (".c", ".h")


def _needs(module: str) -> None:
    if importlib.util.find_spec(module) is None:
        pytest.skip(f"'{module}' is not installed: cannot build a wheel without the build tooling "
                    f"(pip install {module})")


def _expected() -> set[str]:
    """Paths inside the wheel of every module and data file of the four rooms."""
    out = set()
    for room in ROOMS:
        for path in (ROOT / room).rglob("*"):
            if "__pycache__" in path.parts or not path.is_file():
                continue
            if not (path.parent / "__init__.py").exists():
                continue                       # not inside a package: not shipped, not expected
            if path.suffix == ".py" or path.suffix in DATA_SUFFIXES:
                out.add(f"symkf/{room}/{path.relative_to(ROOT / room).as_posix()}")
    return out


@pytest.fixture(scope="module")
def wheel_files(tmp_path_factory) -> set[str]:
    _needs("setuptools")
    _needs("wheel")
    _needs("pip")
    src, out = tmp_path_factory.mktemp("src"), tmp_path_factory.mktemp("wheel")
    for name in ("pyproject.toml", "setup.py", "README.md"):
        shutil.copy(ROOT / name, src / name)
    for room in ("package", *ROOMS):           # a copy: building writes build/ and *.egg-info beside the sources
        shutil.copytree(ROOT / room, src / room, ignore=shutil.ignore_patterns("__pycache__"))
    proc = subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation",
                           "--no-index", "-w", str(out), str(src)], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    (wheel,) = out.glob("symkf-*.whl")
    with zipfile.ZipFile(wheel) as archive:
        return set(archive.namelist())


def test_every_package_folder_is_in_the_wheel(wheel_files):
    packages = {f"symkf/{room}/{init.parent.relative_to(ROOT / room).as_posix()}/__init__.py".replace("/./", "/")
                for room in ROOMS for init in (ROOT / room).rglob("__init__.py") if "__pycache__" not in init.parts}
    missing = sorted(packages - wheel_files)
    assert not missing, f"package folders missing from the wheel: {missing}"


def test_every_module_and_data_file_is_in_the_wheel(wheel_files):
    missing = sorted(_expected() - wheel_files)
    assert not missing, f"files missing from the wheel (a regular install would not have them): {missing}"
    data = {name for name in wheel_files if name.endswith(DATA_SUFFIXES)}
    assert "symkf/runtime/_fastcall.c" in data


def test_the_top_package_carries_its_version_and_docstring(wheel_files):
    assert "symkf/__init__.py" in wheel_files


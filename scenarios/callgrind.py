"""Instruction counts of the generated C under callgrind (deterministic, unlike wall time on a
shared machine), for the benches' ``--instructions`` options (``symkf bench launcher``,
``symkf bench marg``): a small C driver compiled against a bundle's library with the bundle's
own flags, run under ``valgrind --tool=callgrind``, and per-function counts from
``callgrind_annotate``. The drivers are ``.c`` files beside their bench, shipped as package data."""
from __future__ import annotations

import importlib.resources
import json
import re
import subprocess
from pathlib import Path

from symkf.codegen.compilation import compiler

_ANNOTATED_LINE = re.compile(r"^\s*([\d,]+) \([^)]*\)\s+\S*?:(\w+)", re.M)


def driver_source(package: str, name: str) -> str:
    """The text of the C driver ``name`` shipped in ``package`` (a ``.c`` file beside its bench)."""
    return importlib.resources.files(package).joinpath(name).read_text()


def compile_driver(directory: Path, source: str, exe: Path, defines: tuple[str, ...] = ()) -> Path:
    """Compile the C ``source`` into ``exe``, linked against the bundle in ``directory`` with the
    bundle's optimization flags (so the driver measures the library as the filters load it)."""
    manifest = json.loads((directory / "manifest.json").read_text())
    c_file = exe.with_suffix(".c")
    c_file.write_text(source)
    subprocess.run(compiler().split() + ["-std=c99", *manifest["optimization"].split(), *defines, f"-I{directory}",
                                         "-o", str(exe), str(c_file), str(directory / manifest["hashed_library"]), "-lm"],
                   check=True, capture_output=True, text=True)
    return exe


def run(command: list[str], stdin: str | bytes, out: Path) -> tuple[int, str | bytes]:
    """(instructions collected, the program's stdout) of ``command`` under callgrind; the profile
    is written to ``out`` for :func:`function_counts`."""
    proc = subprocess.run(["valgrind", "--tool=callgrind", f"--callgrind-out-file={out}", *command], input=stdin,
                          capture_output=True, text=isinstance(stdin, str), check=True)
    stderr = proc.stderr if isinstance(proc.stderr, str) else proc.stderr.decode()
    return int(re.search(r"Collected : (\d+)", stderr).group(1)), proc.stdout


def function_counts(out: Path, inclusive: bool = False, threshold: int | None = 100) -> dict[str, int]:
    """Instructions of each function in a callgrind profile: exclusive counts summed over the
    profile's entries of one name, or inclusive counts (the largest entry of a name)."""
    options = [f"--inclusive={'yes' if inclusive else 'no'}"] + ([f"--threshold={threshold}"] if threshold else [])
    text = subprocess.run(["callgrind_annotate", *options, str(out)], capture_output=True, text=True).stdout
    counts: dict[str, int] = {}
    for number, name in _ANNOTATED_LINE.findall(text):
        value = int(number.replace(",", ""))
        counts[name] = max(counts.get(name, 0), value) if inclusive else counts.get(name, 0) + value
    return counts

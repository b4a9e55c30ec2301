"""The model author's loop, timed: cold build, no-op load, one-line edit -> loaded filter.

    symkf bench build [--repeats N] [--models launcher,geo_satellite] [--set KEY=VALUE] [--json]

For each model (default: the launcher and the 17-state geo satellite), each repeat starts from an
empty build folder and object cache (``$SYMKF_BUILD_DIR`` pointed at a temporary folder) and a
copy of the paper model written as a user's file outside the package (its relative imports made
absolute), then, all in this process, as a notebook user would:

- cold: ``load(path)`` and a filter made from it (generate + write + compile + load);
- no-op: ``load(path)`` again (execute the file, hash, verify the library's SHA-256, dlopen);
- edit: one line of the file changed (launcher: the density scale height 7.2 -> 7.3 km;
  geo: Table 2's I_xy 53 -> 54 kg m^2), then ``load(path)`` and a filter.

Medians of ``--repeats``, with where the time went for the edit (executing the model and
hashing; generating the kernels and their C, part by part; writing the API unit, header and
Makefile; waiting for the compilers and linking), and the CPU seconds of the cold build and of the
edit (this process, and the compilers it ran: less noisy than wall time on a shared machine). The
phases overlap: each part's units compile while the next part is generated.
Targets (2 cores): no-op <= 0.3 s; edit -> filter <= 3 s (launcher), <= 4 s (geo).
"""
from __future__ import annotations

import json
import os
import re
import resource
import statistics
import tempfile
from pathlib import Path

import numpy as np

from symkf.models import MODELS_DIR
from symkf.scenarios import timing
from symkf.scenarios.report import emit

#: The one-line edit per model (old, new) and the target for edit -> loaded filter (s).
EDITS = {"launcher": ("SCALE_HEIGHT = 7.2e3", "SCALE_HEIGHT = 7.3e3"),
         "geo_satellite": ('"Ixy": 53.0,', '"Ixy": 54.0,')}
TARGETS = {"noop_s": 0.3, "edit_s": {"launcher": 3.0, "geo_satellite": 4.0}}


def add_arguments(parser) -> None:
    parser.add_argument("--repeats", type=int, default=3, help="runs per measurement (median)")
    parser.add_argument("--models", default="launcher,geo_satellite", help="comma-separated paper models")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="a codegen option for every build (e.g. optimization=-O1)")
    parser.add_argument("--json", action="store_true", help="print the results as JSON")


def user_copy(name: str, folder: Path) -> Path:
    """The paper model ``name`` written as a user's file in ``folder`` (absolute imports)."""
    text = (MODELS_DIR / f"{name}.py").read_text()
    text = re.sub(r"^from \.(\w+) import", r"from symkf.models.\1 import", text, flags=re.M)
    text = re.sub(r"^from \. import", "from symkf.models import", text, flags=re.M)
    path = folder / f"{name}.py"
    path.write_text(text)
    return path


def _loaded_filter(path: Path, overrides: dict):
    """load(path) and an EKF (or the model's first filter family) made from it."""
    from symkf.runtime import load
    compiled = load(str(path), backend="compiled", **overrides)
    n = len(compiled.model["states"])
    if "ekf_predict" in compiled.backend.kernels:
        compiled.ekf(np.zeros(n), np.eye(n), np.eye(n))
    return compiled


def one_run(name: str, overrides: dict) -> dict:
    """Cold, no-op and edit timings of one model in a fresh build folder."""
    old, new = EDITS[name]
    previous = os.environ.get("SYMKF_BUILD_DIR")
    with tempfile.TemporaryDirectory(prefix=f"symkf-bench-build-{name}-") as tmp:
        os.environ["SYMKF_BUILD_DIR"] = str(Path(tmp) / "build")
        try:
            path = user_copy(name, Path(tmp))
            cpu = _cpu_seconds()
            _, cold, _ = timing.timed(lambda: _loaded_filter(path, overrides))
            cold_cpu = {key: value - cpu[key] for key, value in _cpu_seconds().items()}
            noop_model, noop, _ = timing.timed(lambda: _loaded_filter(path, overrides))
            assert noop_model.build.up_to_date
            text = path.read_text()
            if old not in text:
                raise RuntimeError(f"bench build: the line to edit ({old}) is not in models/{name}.py")
            path.write_text(text.replace(old, new, 1))
            cpu = _cpu_seconds()
            edited, edit, _ = timing.timed(lambda: _loaded_filter(path, overrides))
            edit_cpu = {key: value - cpu[key] for key, value in _cpu_seconds().items()}
            assert not edited.build.up_to_date
            sources = json.loads(edited.build.manifest.read_text())["sources"]
            lines = sum(len((edited.build.directory / s).read_text().splitlines()) for s in sources)
        finally:
            if previous is None:
                os.environ.pop("SYMKF_BUILD_DIR", None)
            else:
                os.environ["SYMKF_BUILD_DIR"] = previous
    return {"cold_s": cold, "noop_s": noop, "edit_s": edit, "edit_phases_s": edited.build.timings,
            "cold_cpu_s": cold_cpu, "edit_cpu_s": edit_cpu, "edit_units_compiled": len(edited.build.compiled), "units": len(sources),
            "generated_c_lines": lines}


def _cpu_seconds() -> dict:
    """CPU seconds (user + system) of this process ("python") and of its finished children
    ("compilers": every compiler it ran), less noisy than wall time on a shared machine."""
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return {"python": own.ru_utime + own.ru_stime, "compilers": children.ru_utime + children.ru_stime}


def measure(name: str, repeats: int, overrides: dict | None = None) -> dict:
    """Medians over ``repeats`` runs of :func:`one_run`, with the samples."""
    runs = [one_run(name, overrides or {}) for _ in range(max(1, repeats))]
    result = {key: statistics.median(r[key] for r in runs) for key in ("cold_s", "noop_s", "edit_s")}
    phases = runs[0]["edit_phases_s"].keys()
    result["edit_phases_s"] = {p: statistics.median(r["edit_phases_s"][p] for r in runs) for p in phases}
    for key in ("cold_cpu_s", "edit_cpu_s"):
        result[key] = {p: statistics.median(r[key][p] for r in runs) for p in ("python", "compilers")}
    for key in ("generated_c_lines", "units", "edit_units_compiled"):
        result[key] = runs[0][key]
    result["samples"] = {key: [r[key] for r in runs] for key in ("cold_s", "noop_s", "edit_s")}
    result["meets_targets"] = {"noop": result["noop_s"] <= TARGETS["noop_s"],
                               "edit": result["edit_s"] <= TARGETS["edit_s"][name]}
    return result


def _overrides(items: list[str]) -> dict:
    out = {}
    for item in items:
        key, _, value = item.partition("=")
        try:
            out[key] = json.loads(value)
        except ValueError:
            out[key] = value
    return out


def run(args) -> int:
    overrides = _overrides(args.set)
    names = [n for n in args.models.split(",") if n]
    unknown = [n for n in names if n not in EDITS]
    if unknown:
        raise SystemExit(f"symkf bench build: no edit defined for {unknown}; choose from {sorted(EDITS)}")
    results = {name: measure(name, args.repeats, overrides) for name in names}
    results["_settings"] = {"repeats": args.repeats, "overrides": overrides, "cores": os.cpu_count(),
                            "load_average": os.getloadavg()}
    emit(results, None, args.json, lambda r: _print(r, names, args.repeats, overrides))
    return 0


def _print(results: dict, names: list[str], repeats: int, overrides: dict) -> None:
    print(f"model author's loop, medians of {repeats} (s); load average at the end "
          f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores" + (f"; options {overrides}" if overrides else ""))
    print(f"{'model':15s} {'cold build':>11s} {'no-op load':>11s} {'edit->filter':>13s} {'target':>7s}   "
          "edit: model+hash / generate+C / write / compile (s)   edit CPU s: python + compilers   units compiled")
    for name in names:
        r, p, cpu = results[name], results[name]["edit_phases_s"], results[name]["edit_cpu_s"]
        print(f"{name:15s} {r['cold_s']:11.2f} {r['noop_s']:11.3f} {r['edit_s']:13.2f} "
              f"{TARGETS['edit_s'][name]:7.1f}   {p.get('model', 0):.2f} / {p.get('generate', 0):.2f} / "
              f"{p.get('write', 0):.2f} / {p.get('compile', 0):.2f}   {cpu['python']:.2f} + {cpu['compilers']:.2f}   "
              f"{r['edit_units_compiled']} of {r['units']} ({r['generated_c_lines']} lines of C)")

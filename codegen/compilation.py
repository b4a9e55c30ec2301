"""The C compiler: its identity, the flags of each unit, and the units compiled to one library.

:class:`UnitCompiler` compiles a build's units while the build goes on (one compiler per core),
each object cached in ``<root>/.objects`` by the hash of the compiler, flags and the unit's text
(the preprocessor's output for the units that include the header), so an edit of the dynamics
recompiles the functions that evaluate the dynamics only. :func:`compile_bundle` links them.
"""
from __future__ import annotations

import fnmatch
import functools
import hashlib
import json
import os
import secrets
import shutil
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path

from .c_backend import lanes as c_lanes, lockstep as c_lockstep, makefile as c_makefile, stack as c_stack
from .compiler_pool import CompilerPool, run_compiler, run_compilers
from .errors import BuildError, CompilerNotFound
from .manifest import sha256_bytes, sha256_file
from .safe_files import check_folder, read_checked, write_exclusive
from .spec import CodegenConfig, ConfigError, declare_options, option


def compiler() -> str:
    """The C compiler command ($CC or cc); raises CompilerNotFound with a one-line message."""
    cc = os.environ.get("CC", "cc")
    if not cc.split() or shutil.which(cc.split()[0]) is None:
        raise CompilerNotFound(f"no C compiler found ('{cc}'): install gcc or clang, or set CC")
    return cc


@functools.lru_cache(maxsize=8)
def compiler_identity(cc: str) -> str:
    """The compiler's path and first line of ``--version`` (cached per process)."""
    argv = cc.split()
    try:
        proc = subprocess.run(argv + ["--version"], capture_output=True, text=True, timeout=30)
        version = (proc.stdout or proc.stderr).splitlines()[0] if (proc.stdout or proc.stderr) else ""
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise CompilerNotFound(f"C compiler '{cc}' does not run: {exc}") from None
    return f"{shutil.which(argv[0])} {' '.join(argv[1:])}: {version}".strip()


def compile_flags(config: CodegenConfig, unit: str = "", host: bool = True) -> list[str]:
    """Flags of a unit (:func:`unit_optimization`), in the library and in the bundle's Makefile alike,
    but for the library's SIMD lanes (c_backend/lanes.py ``host_flags``: the Makefile has none;
    ``host=False``: the bundle's flags)."""
    return (c_makefile.STRICT_FLAGS.split() + unit_optimization(config, unit).split() + ["-fPIC"]
            + c_makefile.precision_flags(config)
            + (c_lanes.host_flags(config, unit) + c_lockstep.host_flags(config, unit) if host else []))


def compiler_failure(what: str, cmd: list[str], stderr: str, directory: Path) -> BuildError:
    """The error of a failed compiler command: one line for a fault of the disk (full, read-only),
    which is not the code's; else the command and the compiler's own message."""
    space = "free some space, or set SYMKF_BUILD_DIR to a folder on another disk"
    for sign, fault, fix in (("No space left on device", "the disk is full", space),
                             ("Disk quota exceeded", "the disk quota is used up", space),
                             ("Read-only file system", "the folder is read-only",
                              "set SYMKF_BUILD_DIR to a folder you can write")):
        if sign in stderr:
            return BuildError(f"{what} failed: {fault} ({directory.parent}); nothing was installed: {fix}")
    return BuildError(f"{what} failed ({' '.join(cmd)}):\n{stderr[-4000:]}")


@dataclass(frozen=True)
class UnitOptions:
    """Per-unit compiler flags (read by :func:`unit_optimization`)."""

    unit_optimization: dict = option(None, "{shell pattern of unit file names: -O flags} for those units "
                                           "(default: every unit gets optimization)")


declare_options(UnitOptions, "symkf.codegen.compilation")


def unit_optimization(config: CodegenConfig, unit: str = "") -> str:
    """The -O flags of one unit: those of the first shell pattern in the codegen option
    ``unit_optimization`` ({pattern of unit file names: flags}, e.g. ``{"*_k_ekf_step_*":
    "-O2 -fno-math-errno"}``) that matches its file name, else ``config.optimization``."""
    table = config.get("unit_optimization") or {}
    if not isinstance(table, dict) or not all(isinstance(k, str) and isinstance(v, str) and v.startswith("-O")
                                              for k, v in table.items()):
        raise ConfigError(f"unit_optimization: expected {{unit file pattern: flags starting with -O}}, got {table!r}")
    return next((flags for pattern, flags in table.items() if fnmatch.fnmatchcase(unit, pattern)), config.optimization)


@functools.lru_cache(maxsize=8)
def measures_stack(cc: str) -> bool:
    """Whether the compiler writes call graphs with stack frames (GCC >= 10; clang does not)."""
    with tempfile.TemporaryDirectory() as tmp:
        (Path(tmp) / "probe.c").write_text("int symkf_probe(void);\nint symkf_probe(void) { return 0; }\n")
        returncode, _ = run_compiler(cc.split() + c_makefile.STACK_FLAGS.split() + ["-c", "-o", "probe.o", "probe.c"],
                                     Path(tmp))
        return returncode == 0 and (Path(tmp) / "probe.ci").is_file()


def compile_bundle(directory: Path, name: str, cc: str, config: CodegenConfig,
                   units: UnitCompiler | None = None) -> list[str]:
    """Compile the manifest's units in parallel (:class:`UnitCompiler`: one compiler per core; a
    unit whose text, compiler and flags match a cached object is not recompiled; ``units``: the
    compiler the build already started units with), fill the header's stack figures from the
    compiler's call graphs of those same compiles, link lib<name>.so, copy it to the per-build name
    Python loads and record the SHA-256 of that copy and of every file of the bundle. Returns the
    units compiled."""
    manifest = json.loads((directory / "manifest.json").read_text())
    if units is None:
        with UnitCompiler(directory, cc, config, f"{name}.h") as units:
            units.add({file: (directory / file).read_text() for file in manifest["sources"]})
            return compile_bundle(directory, name, cc, config, units)
    objects, compiled = units.finish(manifest["sources"])
    graphs = "".join(obj.with_suffix(".ci").read_text() for obj in objects) if units.stack else None
    header = directory / f"{name}.h"
    header.write_text(c_stack.fill_stack(header.read_text(), c_stack.stack_usage(graphs) if units.stack else None))
    cmd = cc.split() + ["-shared", "-o", f"lib{name}.so"] + [o.name for o in objects] + ["-lm"]
    returncode, stderr = run_compiler(cmd, directory)
    if returncode != 0:
        raise compiler_failure(f"linking lib{name}.so", cmd, stderr, directory)
    for obj in objects:
        for leftover in (obj, obj.with_suffix(".ci"), obj.with_suffix(".su")):
            leftover.unlink(missing_ok=True)
    loaded = f"lib{name}.{manifest['content_hash'][:12]}.{secrets.token_hex(4)}.so"
    shutil.copyfile(directory / f"lib{name}.so", directory / loaded)        # a copy, never a hard link
    bundle = list(manifest["sources"]) + [f"{name}.h", "Makefile", f"lib{name}.so"]
    manifest.update(hashed_library=loaded, library_sha256=sha256_file(directory / loaded),
                    files={file: sha256_file(directory / file) for file in bundle})   # the bundle is verified too
    (directory / "manifest.json").write_text(json.dumps(manifest, indent=1))
    return compiled


@dataclass
class _Unit:
    text: str
    cached: Path | None = None           # its object cache entry (None: not keyed yet)
    job: int | None = None               # its compile in the pool (None: the object came from the cache)
    stack_job: int | None = None         # the compile of its call graph with the bundle's flags, if apart


class UnitCompiler:
    """A build's C units compiled to objects while the build goes on: each unit as soon as its text
    is known (:meth:`add`: written, then compiled in the background, largest first, one compiler
    per core but one while this process is still generating), then :meth:`finish` waits for them.

    Objects are cached in ``<root>/.objects``: an entry ``<key>.o`` (+ ``<key>.ci``, the call graph
    with stack frames) is named by the hash of the compiler's identity, the unit's flags and its
    text, or for a unit that includes the header (the API and hash units) the preprocessor's output
    (``cc -E``, line markers kept: the header's comments, the content hash it quotes and macros the
    unit does not use, such as a model constant, do not recompile it). An entry is vouched for by
    ``<key>.sum``, the SHA-256 of its files, written last: one whose copies do not match their sums
    (damaged, replaced, half written) is recompiled, never linked."""

    def __init__(self, directory: Path, cc: str, config: CodegenConfig, header: str, jobs: int | None = None,
                 progress=None):
        self.directory, self.cc, self.config, self.header = directory, cc, config, header
        self.progress = progress             # a codegen.progress.BuildProgress, or None
        self.stack = measures_stack(cc)
        self.suffixes = (".o", ".ci") if self.stack else (".o",)
        self.cache = check_folder(directory.parent / ".objects", create=True)     # this user's, or refused
        self.jobs = max(1, jobs or os.cpu_count() or 1)
        self.pool = CompilerPool(directory, max(1, self.jobs - 1), cores=self.jobs,     # this process is generating
                                 on_finished=progress.units if progress else None)
        self.units: dict[str, _Unit] = {}

    def __enter__(self) -> "UnitCompiler":
        return self

    def __exit__(self, kind, value, traceback) -> None:
        self.pool.__exit__(kind, value, traceback)

    def flags(self, file: str) -> list[str]:
        return compile_flags(self.config, file) + (c_makefile.STACK_FLAGS.split() if self.stack else [])

    def _stack_apart(self, file: str) -> bool:
        """Whether the unit's call graph needs a compile of its own: a unit the library compiles
        with the hook of its SIMD lanes has other frames than the bundle's (which has no lanes),
        and the header states the bundle's stack."""
        return self.stack and bool(c_lanes.host_flags(self.config, file)) and not file.endswith(("_lanes.c", "_lockstep.c"))

    def _cancel(self, unit: "_Unit") -> None:
        for job in (unit.job, unit.stack_job):
            if job is not None:
                self.pool.cancel(job)

    def add(self, texts: dict[str, str]) -> None:
        """Write these units and start compiling each one whose object is not cached; a unit
        written before with another text is cancelled and restarted. A unit that includes the
        header is keyed (and started) by :meth:`finish`, once the header is written."""
        for file, text in sorted(texts.items(), key=lambda item: -len(item[1])):
            unit = self.units.get(file)
            if unit is not None and unit.text == text:
                continue
            if unit is not None:
                self._cancel(unit)
            (self.directory / file).write_text(text)
            self.units[file] = _Unit(text)
            if f'#include "{self.header}"' not in text:
                self._start(file, text)
        self.pool.poll()

    def _start(self, file: str, keyed_text: str) -> None:
        identity = json.dumps([compiler_identity(self.cc), self.flags(file)])
        unit = self.units[file]
        unit.cached = self.cache / hashlib.sha256((identity + keyed_text).encode()).hexdigest()[:32]
        obj = self.directory / (file[:-2] + ".o")
        if _reuse(unit.cached, obj, self.suffixes):
            return
        if not self._stack_apart(file):
            unit.job = self.pool.submit(self.cc.split() + self.flags(file) + ["-c", "-o", obj.name, file],
                                        priority=len(unit.text))      # the longest compile first
            return
        unit.job = self.pool.submit(self.cc.split() + compile_flags(self.config, file) + ["-c", "-o", obj.name, file],
                                    priority=len(unit.text))
        unit.stack_job = self.pool.submit(self.cc.split() + compile_flags(self.config, file, host=False)
                                          + c_makefile.STACK_FLAGS.split() + ["-c", "-o", file[:-2] + ".stack.o", file],
                                          priority=len(unit.text), counted=False)

    def finish(self, sources: list[str]) -> tuple[list[Path], list[str]]:
        """Start the units that include the header, wait for every compile and cache the new
        objects. Returns the objects of ``sources`` (in order) and the units compiled; units added
        but not in ``sources`` (early ones the final code does not have) are removed."""
        self.pool.jobs = self.jobs                                       # done generating: every core compiles
        for file in set(self.units) - set(sources):
            self._cancel(self.units.pop(file))
            for suffix in (".c", ".o", ".ci", ".su", ".stack.o", ".stack.ci", ".stack.su"):
                (self.directory / (file[:-2] + suffix)).unlink(missing_ok=True)
        waiting = [file for file in sources if self.units[file].cached is None]
        commands = [self.cc.split() + compile_flags(self.config, file) + ["-E", "-o", file[:-2] + ".i", file]
                    for file in waiting]
        for cmd, (returncode, stderr) in zip(commands, run_compilers(commands, self.directory)):
            if returncode != 0:
                raise compiler_failure(f"preprocessing {cmd[-1]}", cmd, stderr, self.directory)
        for file in waiting:
            self._start(file, (self.directory / (file[:-2] + ".i")).read_text())
            (self.directory / (file[:-2] + ".i")).unlink()
        if self.progress is not None:
            self.progress.final = True                                   # every unit is known now
        results = self.pool.wait()
        compiled = [file for file in sources if self.units[file].job is not None]
        for file in compiled:
            for job in (self.units[file].job, self.units[file].stack_job):
                returncode, stderr = results[job] if job is not None else (0, "")
                if returncode != 0:
                    cmd = self.cc.split() + self.flags(file) + ["-c", file]
                    raise compiler_failure(f"compiling {file}", cmd, stderr, self.directory)
        for file in compiled:
            if self.units[file].stack_job is not None:       # the bundle's call graph beside the library's object
                stem = self.directory / file[:-2]
                Path(f"{stem}.stack.ci").replace(f"{stem}.ci")
                for leftover in (".stack.o", ".stack.su"):
                    Path(f"{stem}{leftover}").unlink(missing_ok=True)
            _store(self.units[file].cached, self.directory / (file[:-2] + ".o"), self.suffixes)
        _prune(self.cache, keep=400)
        return [self.directory / (file[:-2] + ".o") for file in sources], compiled


def _reuse(cached: Path, obj: Path, suffixes: tuple[str, ...]) -> bool:
    """Copy a cached entry next to the unit if its bytes match their sums; False (compile) otherwise.
    Each file is read once, without following a symlink and only if this user made it
    (:func:`~symkf.codegen.safe_files.read_checked`: anything else is refused, never linked), and
    only the bytes that matched their sum are written to the staging folder the link reads."""
    try:
        sums = json.loads(read_checked(cached.with_suffix(".sum")))
        verified = {}
        for suffix in suffixes:
            data = read_checked(cached.with_suffix(suffix))
            if sha256_bytes(data) != sums[suffix]:
                return False
            verified[suffix] = data
    except (OSError, ValueError, KeyError, TypeError):
        return False
    for suffix, data in verified.items():
        obj.with_suffix(suffix).write_bytes(data)        # the staging folder: private to this build
    return True


def _store(cached: Path, obj: Path, suffixes: tuple[str, ...]) -> None:
    """Add a compiled unit to the cache: its files, then (last) their sums, each written to an
    exclusively created temporary renamed into place (a planted symlink is never followed)."""
    sums = {}
    for suffix in suffixes:
        data = obj.with_suffix(suffix).read_bytes()
        sums[suffix] = sha256_bytes(data)
        write_exclusive(cached.with_suffix(suffix), data)
    write_exclusive(cached.with_suffix(".sum"), json.dumps(sums))


def _prune(cache: Path, keep: int) -> None:
    """Keep the ``keep`` most recently written cache entries (object, call graph, sums)."""
    entries = sorted(cache.glob("*.sum"), key=lambda p: p.stat().st_mtime, reverse=True)
    for path in entries[keep:]:
        for suffix in (".sum", ".o", ".ci"):
            path.with_suffix(suffix).unlink(missing_ok=True)

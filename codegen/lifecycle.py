"""The build lifecycle: generate -> compile -> install, keyed by a hash of what is generated.

``build_model(model)`` makes ``<root>/<folder>/`` (:mod:`symkf.codegen.build_folders`): the C units,
header, Makefile and ``manifest.json`` (:mod:`symkf.codegen.generation`) and ``lib<name>.so``
(:mod:`symkf.codegen.compilation`), unless the folder is up to date for the content hash
(:mod:`symkf.codegen.hashing`) and its library matches the SHA-256 its manifest records
(:mod:`symkf.codegen.manifest`). The library Python loads is its own copy with a per-build name,
sharing no inode with ``lib<name>.so``.

A build happens in a staging folder moved into place when complete, under a per-folder lock
(opened without following symlinks); staging folders left by a killed build are removed by the
next one, and the compiler dies with the process that started it
(:mod:`symkf.codegen.compiler_pool`). :func:`export_bundle` copies a built bundle anywhere.
"""
from __future__ import annotations

import errno
import fcntl
import json
import os
import shutil
import tempfile
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

from symkf.models import Model, get_model
from .c_backend import units as c_units
from .build_folders import folder_name, private_root
from .compilation import UnitCompiler, compile_bundle, compiler, unit_optimization
from .errors import BuildError, CompilerNotFound
from .generation import check_families, config_for, generate_validated, write_bundle
from .hashing import content_hash, generated_hash
from .manifest import read_manifest, verified_manifest
from .spec import Bundle

#: Files of a bundle exported by ``symkf build X --out DIR`` (``{name}`` = the model's name),
#: besides the C units the manifest lists under "sources".
BUNDLE_FILES = ("{name}.h", "Makefile", "manifest.json", "lib{name}.so")


@dataclass(frozen=True)
class BuildResult:
    """What a build produced (paths) and whether any work was done."""

    model: str
    directory: Path
    library: Path
    manifest: Path
    content_hash: str
    up_to_date: bool
    seconds: float
    #: Where the time went (s): "model" (execute build() + hash), "generate" (kernels and their
    #: C, part by part; each part's units start compiling meanwhile), "write" (API and hash
    #: units, header, Makefile), "compile" (waiting for the units not in the object cache; link).
    timings: dict = field(default_factory=dict)
    #: The C units compiled by this build (the others came from the object cache).
    compiled: tuple = ()
    #: The manifest, as this build wrote it or as the up-to-date check read it (its library
    #: verified then): the runtime opens the library with it and reads the folder no more.
    record: dict = field(default_factory=dict, repr=False, compare=False)


@contextmanager
def _lock(root: Path, folder: str):
    """An exclusive lock per build folder; the lock file is never a followed symlink."""
    try:
        fd = os.open(root / f".{folder}.lock", os.O_WRONLY | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o600)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise BuildError(f"{root / f'.{folder}.lock'} is a symlink; remove it") from None
        raise
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)


def _remove_stale(root: Path, folder: str) -> None:
    """Staging and old folders of ``folder`` left by a killed build (we hold its lock: none is live)."""
    for pattern in (f".{folder}.tmp-*", f".{folder}.old-*"):
        for path in root.glob(pattern):
            shutil.rmtree(path, ignore_errors=True)


def build_model(model, force: bool = False, **overrides) -> BuildResult:
    """Generate and compile the model's build folder unless it is already up to date.

    ``model``: a Model, a module, a paper model's short name, a file path or a module name (see
    :func:`symkf.models.get_model`); a file is executed afresh. Without a C compiler an up-to-date
    library (same generated hash) is still returned; otherwise :class:`CompilerNotFound`.
    """
    start = time.perf_counter()
    return build_validated(get_model(model), force, start, **overrides)


def build_validated(model: Model, force: bool = False, start: float | None = None, **overrides) -> BuildResult:
    """:func:`build_model` of a Model :func:`~symkf.models.get_model` returned (validated: a
    loader that has it does not validate it twice). ``start``: when the caller's timing began."""
    start = time.perf_counter() if start is None else start
    config = config_for(model, **overrides)
    unit_optimization(config)                                   # a bad per-unit option: refused before any work
    check_families(model)                                       # also for a cached build (not regenerated)
    timings = {}
    root = private_root()
    directory = root / folder_name(model, config)
    generated = generated_hash(model, config)
    try:
        cc = compiler()
    except CompilerNotFound:
        if not force and (manifest := verified_manifest(directory, generated, "generated_hash")) is not None:
            return _result(model.name, directory, manifest, True, start)
        raise
    key = content_hash(model, config, cc, generated)
    timings["model"] = time.perf_counter() - start
    if not force and (manifest := verified_manifest(directory, key)) is not None:
        return _result(model.name, directory, manifest, True, start)
    with _lock(root, directory.name):
        if not force and (manifest := verified_manifest(directory, key)) is not None:   # built meanwhile
            return _result(model.name, directory, manifest, True, start)
        _remove_stale(root, directory.name)
        staging = Path(tempfile.mkdtemp(prefix=f".{directory.name}.tmp-", dir=root))
        try:
            with UnitCompiler(staging, cc, config, f"{model.name}.h") as units:
                mark, per_part = time.perf_counter(), {}      # each part's units compile while the next part generates

                def on_part(index: int, part: Bundle) -> None:
                    per_part[index] = c_units.part_units(part)
                    units.add(per_part[index])
                bundle = generate_validated(model, config, on_part)
                timings["generate"] = time.perf_counter() - mark
                write_bundle(bundle, staging, key, generated, cc, units, [per_part[i] for i in sorted(per_part)])
                timings["write"] = time.perf_counter() - mark - timings["generate"]
                mark = time.perf_counter()
                compiled = compile_bundle(staging, model.name, cc, config, units)
                timings["compile"] = time.perf_counter() - mark
            _install(staging, directory)
        except BaseException:
            shutil.rmtree(staging, ignore_errors=True)
            raise
    return _result(model.name, directory, read_manifest(directory) or {}, False, start, timings, compiled)


def _result(name: str, directory: Path, manifest: dict, up_to_date: bool, start: float, timings: dict | None = None,
            compiled: list[str] = ()) -> BuildResult:
    return BuildResult(name, directory, directory / manifest.get("hashed_library", f"lib{name}.so"),
                       directory / "manifest.json", manifest.get("content_hash", ""), up_to_date,
                       time.perf_counter() - start, dict(timings or {}), tuple(compiled), manifest)


def _install(staging: Path, directory: Path) -> None:
    """Swap the finished staging folder into place (two renames; the old one is removed)."""
    old = None
    if directory.exists():
        old = directory.with_name(f".{directory.name}.old-{os.getpid()}-{time.monotonic_ns()}")
        os.rename(directory, old)
    os.chmod(staging, 0o755)
    os.rename(staging, directory)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def export_bundle(result: BuildResult, out: Path) -> list[Path]:
    """Copy the flight bundle (the .c units, .h, Makefile, manifest.json, lib<name>.so) into ``out``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    copied = []
    sources = json.loads(result.manifest.read_text())["sources"]
    for pattern in list(sources) + list(BUNDLE_FILES):
        source = result.directory / pattern.format(name=result.model)
        shutil.copyfile(source, out / source.name)
        copied.append(out / source.name)
    return copied

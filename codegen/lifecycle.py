"""The build lifecycle: generate -> compile -> install, keyed by a hash of what is generated.

``build_model(model)`` makes ``<root>/<folder>@<key16>/`` (:mod:`symkf.codegen.build_folders`;
``<root>/<folder>`` points to it): the C units, header, Makefile and ``manifest.json``
(:mod:`symkf.codegen.generation`) and ``lib<name>.so`` (:mod:`symkf.codegen.compilation`), unless
that folder is complete and every file in it matches the SHA-256 its manifest records
(:mod:`symkf.codegen.manifest`); a folder with a file missing, damaged or edited is regenerated
with a :class:`~symkf.codegen.errors.BundleRepairWarning` saying which. The library Python loads
is its own copy with a per-build name, sharing no inode with ``lib<name>.so``.

A build happens in a staging folder renamed into place when complete, under a lock of its
content hash (opened without following symlinks): two edits of one model build side by side,
each published under its own name, and a load gets the library of exactly the text it read.
Staging folders left by a killed build are removed by the next one, and the compiler dies with
the process that started it (:mod:`symkf.codegen.compiler_pool`). A fault (disk full, a
read-only folder) is a one-line :class:`~symkf.codegen.errors.BuildError` and leaves no
temporary. :func:`~symkf.codegen.export.export_bundle` copies a verified bundle anywhere.
"""
from __future__ import annotations

import errno
import fcntl
import os
import shutil
import tempfile
import time
import warnings
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

from symkf.models import Model, get_model
from . import float_check
from .c_backend import units as c_units
from .build_folders import current, folder_name, keyed_name, point_to, private_root, prune, published
from .compilation import UnitCompiler, compile_bundle, compiler, unit_optimization
from .errors import BuildError, BundleRepairWarning, CompilerNotFound
from .export import export_bundle
from .generation import check_families, config_for, generate_validated, write_bundle
from .hashing import content_hash, generated_hash
from .manifest import folder_state
from .progress import BuildProgress
from .safe_files import ForeignFileError, check_owned
from .spec import Bundle

__all__ = ["BuildResult", "build_model", "build_validated", "export_bundle"]


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
    #: The manifest, as this build wrote it or as the up-to-date check read it (its files
    #: verified then): the runtime opens the library with it and reads the folder no more.
    record: dict = field(default_factory=dict, repr=False, compare=False)
    #: Why an existing build of the same sources was regenerated ("" if it was not), e.g.
    #: "launcher.h is missing".
    repaired: str = ""


@contextmanager
def _lock(root: Path, name: str):
    """An exclusive lock named ``name``: a file of this user's, never a followed symlink."""
    path = root / f".{name}.lock"
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o600)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise BuildError(f"{path} is a symlink; remove it") from None
        raise
    try:
        check_owned(path, os.fstat(fd), "file")
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)


def _remove_stale(root: Path, name: str) -> None:
    """Staging and old folders (and pointer temporaries) of ``name`` left by a killed build."""
    for pattern in (f".{name}.tmp-*", f".{name}.old-*", f".{name}.link-*"):
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
    loader that has it does not validate it twice). ``start``: when the caller's timing began.
    A fault of the file system is a one-line :class:`BuildError` saying what to do."""
    start = time.perf_counter() if start is None else start
    config = config_for(model, **overrides)
    unit_optimization(config)                                   # a bad per-unit option: refused before any work
    check_families(model)                                       # also for a cached build (not regenerated)
    float_check.warn_at_build(model, config)                    # float: what will not resolve, said now
    root = private_root()
    folder = folder_name(model, config)
    try:
        return _build(model, config, root, folder, force, start)
    except OSError as exc:
        raise BuildError(fault_message(exc, model.name, root)) from None


def fault_message(exc: OSError, model: str, root: Path) -> str:
    """One line for a file-system fault while building ``model`` in ``root``: what and what to do."""
    where = f" ({exc.filename})" if exc.filename else ""
    if exc.errno in (errno.ENOSPC, errno.EDQUOT):
        fix = "free some space there, or set SYMKF_BUILD_DIR to a folder on another disk"
        return f"building '{model}': the disk of {root} is full{where}; nothing was installed: {fix}"
    if exc.errno in (errno.EROFS, errno.EACCES, errno.EPERM):
        what = "read-only" if exc.errno == errno.EROFS else "not writable by you"
        return (f"building '{model}': {root} is {what}{where}, and the build there is missing or stale: "
                "make it writable, or set SYMKF_BUILD_DIR to a folder you can write")
    return f"building '{model}' in {root}: {exc.strerror or exc}{where}"


def _build(model: Model, config, root: Path, folder: str, force: bool, start: float) -> BuildResult:
    timings = {}
    generated = generated_hash(model, config)
    try:
        cc = compiler()
    except CompilerNotFound:
        for candidate in [c for c in [current(root, folder)] if c] + published(root, folder):
            if not force and (manifest := folder_state(candidate, generated, "generated_hash")[0]) is not None:
                return _result(model.name, candidate, manifest, True, start)
        raise
    key = content_hash(model, config, cc, generated)
    directory = root / keyed_name(folder, key)
    timings["model"] = time.perf_counter() - start
    if not force and (manifest := folder_state(directory, key)[0]) is not None:
        _point(root, folder, directory)
        return _result(model.name, directory, manifest, True, start)
    with _lock(root, directory.name):                            # keyed by the content hash: one edit, one lock
        manifest, why = folder_state(directory, key)              # re-checked under the lock: built meanwhile?
        if not force and manifest is not None:
            _point(root, folder, directory)
            return _result(model.name, directory, manifest, True, start)
        repaired = "" if force or why in ("not built", "built from other sources") else why
        if repaired:
            warnings.warn(f"{model.name}: {why} in {directory}; regenerating the bundle", BundleRepairWarning,
                          stacklevel=4)
        _remove_stale(root, directory.name)                      # we hold its lock: none of these is live
        staging = Path(tempfile.mkdtemp(prefix=f".{directory.name}.tmp-", dir=root))
        try:
            compiled = _generate_and_compile(model, config, staging, key, generated, cc, timings)
            manifest = folder_state(staging, key)[0] or {}
            _install(staging, directory)
        except BaseException:
            shutil.rmtree(staging, ignore_errors=True)
            raise
    _point(root, folder, directory)
    prune(root, folder)
    _remove_stale(root, folder)                      # an older layout's, or a killed pointer update's
    return _result(model.name, directory, manifest, False, start, timings, compiled, repaired)


def _generate_and_compile(model: Model, config, staging: Path, key: str, generated: str, cc: str,
                          timings: dict) -> list[str]:
    """Write and compile the bundle in ``staging``; the units compiled (others: object cache)."""
    progress = BuildProgress(model.name)
    progress.begin()
    with UnitCompiler(staging, cc, config, f"{model.name}.h", progress=progress) as units:
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
        progress.end(len(compiled), len(units.units))
    return compiled


def _point(root: Path, folder: str, directory: Path) -> None:
    """``<root>/<folder>`` -> ``directory`` (for people and Makefiles; the loader never follows it).
    Best effort: a read-only root keeps its old pointer, and the build is used all the same."""
    try:
        point_to(root, folder, directory)
    except (OSError, ForeignFileError):
        pass


def _result(name: str, directory: Path, manifest: dict, up_to_date: bool, start: float, timings: dict | None = None,
            compiled: list[str] = (), repaired: str = "") -> BuildResult:
    return BuildResult(name, directory, directory / manifest.get("hashed_library", f"lib{name}.so"),
                       directory / "manifest.json", manifest.get("content_hash", ""), up_to_date,
                       time.perf_counter() - start, dict(timings or {}), tuple(compiled), manifest, repaired)


def _install(staging: Path, directory: Path) -> None:
    """Rename the finished staging folder into place (a damaged folder there is moved away first)."""
    os.chmod(staging, 0o755)
    try:
        os.rename(staging, directory)
        return
    except OSError as exc:
        if exc.errno not in (errno.ENOTEMPTY, errno.EEXIST):
            raise
    old = directory.with_name(f".{directory.name}.old-{os.getpid()}-{time.monotonic_ns()}")
    os.rename(directory, old)                           # we hold this key's lock: nobody else installs it
    os.rename(staging, directory)
    shutil.rmtree(old, ignore_errors=True)

"""The checked fast path of one filter step: a small C extension, built at first use.

``Filter.step(t, dt, z, q=...)`` with float64 arrays of the right shape is the call a tracker
makes thousands of times a second. Through the Python contract it costs tens of microseconds
(type and shape checks, dict handling, copies, a ctypes call); :file:`_fastcall.c` does the same
checks, copies and kernel call in C. The rules stay in :mod:`symkf.runtime.contract`:
the extension accepts only calls the contract accepts, writes the same values, and returns None
(having written nothing) for anything else, which the Python path then accepts or refuses.

The extension is compiled once per machine and Python, like a model library: with the C compiler
of :func:`symkf.codegen.compilation.compiler` and Python's headers, into ``<build root>/_fastcall/<key>/``
(key: SHA-256 of the C source, compiler, Python ABI and flags), its SHA-256 checked before it is
imported. Those folders, the extension and its ``sha256`` record are used only if this user made
them (:mod:`symkf.codegen.safe_files`: checked owner and mode, opened without following a
symlink; the record written to an exclusively created temporary and renamed); anything foreign
is refused with a warning naming it, and every call takes the Python path. Without a compiler, without Python's headers, on the CasADi-VM backend or with
``SYMKF_FASTCALL=0``, every call takes the Python path (same results, slower).
"""
from __future__ import annotations

import functools
import hashlib
import importlib.machinery
import importlib.util
import inspect
import os
import sys
import sysconfig
import tempfile
import warnings
from pathlib import Path

import numpy

from symkf.codegen.build_folders import private_root
from symkf.codegen.compilation import compiler, compiler_identity
from symkf.codegen.compiler_pool import run_compiler
from symkf.codegen.errors import BuildError
from symkf.codegen.lifecycle import _lock
from symkf.codegen.manifest import sha256_file
from symkf.codegen.safe_files import (ForeignFileError, check_folder, mapped_is, open_checked, read_checked,
                                      sha256_fd, write_exclusive)
from symkf.codegen.spec import STATUS_GATED

SOURCE = Path(__file__).resolve().parent / "_fastcall.c"
MODULE = "_symkf_fastcall"
FLAGS = ("-std=c99", "-O2", "-fPIC", "-shared", "-Wall", "-Wextra", "-Wno-unused-parameter",
         "-Wno-missing-field-initializers", "-Wno-cast-function-type")

#: Why the extension is not in use (None when it is); set by :func:`extension`.
unavailable: str | None = None


@functools.lru_cache(maxsize=1)
def extension():
    """The compiled ``_symkf_fastcall`` module, built if needed; None if it cannot be (see
    :data:`unavailable`)."""
    global unavailable
    if os.environ.get("SYMKF_FASTCALL", "1") == "0":
        unavailable = "disabled by SYMKF_FASTCALL=0"
        return None
    try:
        module = _import(_build())
    except ForeignFileError as exc:
        unavailable = str(exc)
        warnings.warn(f"the fast path is off: {exc}", RuntimeWarning, stacklevel=2)
        return None
    except (BuildError, OSError, ImportError) as exc:
        unavailable = f"{type(exc).__name__}: {exc}"
        return None
    unavailable = None
    return module


def _numpy_flags() -> list[str]:
    """Read exact ndarrays from their fields (numpy's headers, shipped with numpy); else [] and
    every array goes through the buffer protocol."""
    include = Path(numpy.get_include())
    if not (include / "numpy" / "arrayobject.h").is_file():
        return []
    return ["-DSYMKF_NUMPY", f"-I{include}", f"-DSYMKF_NUMPY_VERSION={numpy.__version__}"]


def _key(cc: str, include: str) -> str:
    text = "\n".join([SOURCE.read_text(), compiler_identity(cc), " ".join(FLAGS + tuple(_numpy_flags())), include,
                      sysconfig.get_config_var("EXT_SUFFIX") or "", sys.version])
    return hashlib.sha256(text.encode()).hexdigest()


def _build() -> Path:
    """``<build root>/_fastcall/<key16>/_symkf_fastcall<EXT_SUFFIX>``, compiled unless present."""
    cc = compiler()
    include = sysconfig.get_paths()["include"]
    if not (Path(include) / "Python.h").is_file():
        raise BuildError(f"Python's headers are not installed (no {include}/Python.h)")
    key = _key(cc, include)
    root = check_folder(private_root() / "_fastcall", create=True)
    folder = root / key[:16]
    library = folder / f"{MODULE}{sysconfig.get_config_var('EXT_SUFFIX') or '.so'}"
    with _lock(root, key[:16]):
        check_folder(folder, create=True)
        if not _verified(folder, library):
            _compile(cc, include, folder, library)
    return library


def _recorded(folder: Path) -> str:
    """The SHA-256 the build recorded for the extension ("" if there is none)."""
    try:
        return read_checked(folder / "sha256").decode().strip()
    except FileNotFoundError:
        return ""


def _verified(folder: Path, library: Path) -> bool:
    try:
        fd = open_checked(library)
    except FileNotFoundError:
        return False
    try:
        return (recorded := _recorded(folder)) != "" and recorded == sha256_fd(fd)
    finally:
        os.close(fd)


def _compile(cc: str, include: str, folder: Path, library: Path) -> None:
    staging = Path(tempfile.mkdtemp(prefix=".tmp-", dir=folder))
    partial = staging / library.name
    try:
        cmd = cc.split() + list(FLAGS) + _numpy_flags() + [f"-I{include}", "-o", str(partial), str(SOURCE), "-lm"]
        code, stderr = run_compiler(cmd, folder)
        if code != 0:
            raise BuildError(f"compiling {SOURCE.name} failed ({' '.join(cmd)}):\n{stderr[-2000:]}")
        os.chmod(partial, 0o755)
        os.replace(partial, library)
    finally:
        partial.unlink(missing_ok=True)
        staging.rmdir()
    write_exclusive(folder / "sha256", sha256_file(library))


def _import(library: Path):
    """Import the extension, only as the file whose SHA-256 matches the record (see :func:`_build`)."""
    fd = open_checked(library)
    try:
        if sha256_fd(fd) != _recorded(library.parent):
            raise ImportError(f"{library} does not match its recorded SHA-256; not imported")
        loader = importlib.machinery.ExtensionFileLoader(MODULE, str(library))
        spec = importlib.util.spec_from_file_location(MODULE, library, loader=loader)
        module = importlib.util.module_from_spec(spec)
        if not mapped_is(fd, library):
            raise ImportError(f"{library} was replaced while it was being imported")
        loader.exec_module(module)
        return module
    finally:
        os.close(fd)


def step(bound, t, dt, clock, slots: list[tuple], keep_alive, trusted: tuple | None = None):
    """A ``Step`` over a bound compiled kernel, or None without the extension or a C kernel.

    Args:
        bound: a :class:`~symkf.runtime.backends.BoundCall` of the compiled backend.
        t, dt: the kernel's time and step-length buffers (None if it has none).
        clock: the filter's time, a float64 buffer of one entry: set to t + dt by a successful
            step; a call with t None starts at it.
        slots: per array argument of the Python call, ``(buffer or None, if_none, check)`` with
            ``if_none`` one of "keep", "ones", "zeros", "decline", "absent" and ``check``
            "finite", "mask" (exactly 0 or 1; one slot at most) or "used" (finite where the
            mask slot uses the component: a measurement z, whose masked components the kernel
            never reads).
        keep_alive: what owns the buffers (held by the Step).
        trusted: ``(bound_trusted, own, stale, saves)`` or None: the kernel called instead once a
            step succeeded while ``own[0]`` is 1 (a bound call over the same buffers), the filter's
            and the measurement's one-entry flags, and ``saves``, ``(bound, replay, carried)``
            per buffer a trusted step keeps for the replay of its diagnostics (``carried``: one
            the kernel writes, x or P; see ``_fastcall.c``). Left out (the Step checks every
            step) where a buffer is not float64.

    Calling the Step returns the status code (0 or SYMKF_GATED), or None having written nothing
    (or, after a kernel failure, having written only the kernel's input buffers): the caller's
    Python path then accepts or refuses the call. ``Step.calls`` counts the calls it took.
    """
    ext = extension()
    if ext is None or getattr(bound, "c_address", None) is None:
        return None
    buffers = [b for b, _, _ in slots] + [t, dt, clock]
    if any(b is not None and (b.size > ext.MAX_SIZE or b.ndim != 1 or b.dtype != float or not b.flags.c_contiguous)
           for b in buffers):
        return None                      # a float32 build, a long or unusual buffer: the Python path
    if_none = {"keep": ext.NONE_KEEP, "ones": ext.NONE_ONES, "zeros": ext.NONE_ZEROS,
               "decline": ext.NONE_DECLINE, "absent": ext.ABSENT}
    check = {"finite": ext.CHECK_FINITE, "mask": ext.CHECK_MASK, "used": ext.CHECK_USED}
    table = tuple((None if b is None else b.ctypes.data, 0 if b is None else b.size, if_none[n], check[c])
                  for b, n, c in slots)
    address = [None if b is None else b.ctypes.data for b in (t, dt, clock)]
    part = _trusted_part(ext, trusted)
    return ext.Step(bound.c_address, bound.c_args, *address, table, STATUS_GATED, (keep_alive, bound, clock, trusted),
                    part)


def _trusted_part(ext, trusted: tuple | None):
    """The Step's trusted part (addresses) of :func:`step`'s ``trusted``, or None."""
    if trusted is None:
        return None
    bound, own, stale, saves = trusted
    buffers = [own, stale] + [array for pair in saves for array in pair[:2]]
    if (getattr(bound, "c_address", None) is None or len(saves) > ext.MAX_SAVES
            or sum(a.size for a, _, carried in saves if carried) > ext.MAX_SAVED
            or any(b.dtype != float or not (b.flags.c_contiguous or b.flags.f_contiguous) for b in buffers)
            or any(a.shape != b.shape or a.strides != b.strides for a, b, _ in saves)):
        return None
    table = tuple((a.ctypes.data, b.ctypes.data, a.size, int(carried))
                  for a, b, carried in sorted(saves, key=lambda save: not save[2]))     # the carried first
    return bound.c_address, bound.c_args, own.ctypes.data, stale.ctypes.data, table


def method(function, owner, default, arguments: tuple, steps: dict | None = None, select: str | None = None,
           result=None):
    """``owner``'s step method ``function`` with its plain calls taken in C, or None without the
    extension or a default Step.

    The returned ``Method`` is called like ``function.__get__(owner)`` (same parameters, positional
    or by keyword) and runs a :func:`step` without a Python frame; every call it does not take goes
    to that bound method with the same arguments (see ``_fastcall.c``). Its ``calls`` counts the
    calls it took.

    Args:
        function: the Python method (its parameters after ``self``: required ones first, every
            other one defaulting to None, except ``nan`` defaulting to "raise").
        owner: the filter.
        default: the Step of a call that names no measurement (None: a call must name one; the
            Python method says so).
        arguments: per argument of the Step (t, dt, then its slots), the name of the parameter
            that gives it, or None (the Step gets None: e.g. t, the filter's clock).
        steps, select: the Step of each measurement name, and the parameter naming it.
        result: returned by a call the Method took (e.g. the state view); None: the status code.
    """
    ext = extension()
    # names interned: a call's literal ("radar") is then found by identity, not by comparing text
    steps = None if select is None else {sys.intern(name): s for name, s in steps.items() if s is not None}
    if ext is None or (default is None and not steps):
        return None
    names, required = _parameters(function)
    index = {name: i for i, name in enumerate(names)}
    return ext.Method(function.__get__(owner), names, required, index.get("nan", -1),
                      -1 if select is None else index[select], steps, default,
                      tuple(-1 if a is None else index[a] for a in arguments), result)


@functools.lru_cache(maxsize=None)
def _parameters(function) -> tuple[tuple[str, ...], int]:
    """(names, number of required ones) of a step method's parameters after ``self``, checked."""
    parameters = list(inspect.signature(function).parameters.values())[1:]
    for p in parameters:
        default_ok = p.default is p.empty or p.default is None or (p.name == "nan" and p.default == "raise")
        if p.kind is not p.POSITIONAL_OR_KEYWORD or not default_ok:
            raise TypeError(f"fastcall.method: parameter {p.name!r} of {function.__qualname__} must be "
                            "positional-or-keyword and default to None (nan: 'raise')")
    return tuple(p.name for p in parameters), sum(p.default is p.empty for p in parameters)

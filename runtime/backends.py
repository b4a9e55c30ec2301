"""Two ways to call a kernel on numpy buffers: the compiled library (ctypes) or CasADi's VM.

Both expose the same :class:`BoundCall` — a kernel bound once to a fixed set of numpy buffers,
called with no arguments, returning the status code — so filters never know which one runs.
The compiled path passes one pointer array to ``<model>_<kernel>_v``: the call does no
allocation and no conversion. ctypes releases the GIL during the call, so Monte Carlo runs can
use threads.
"""
from __future__ import annotations

import ctypes
import functools
import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from symkf.codegen.lifecycle import BuildResult
from symkf.codegen.manifest import verified_manifest
from symkf.codegen.safe_files import mapped_is, open_checked, sha256_fd
from symkf.codegen.c_backend.api import passing
from symkf.codegen.spec import STATUS_CODES, STATUS_GATED, STATUS_NONFINITE, Arg, Bundle, Kernel


class SymkfError(RuntimeError):
    """A kernel returned a non-zero code; ``code`` and ``name`` say which failure it was."""

    def __init__(self, kernel: str, code: int, detail: str = ""):
        name, meaning = STATUS_CODES.get(code, (f"code {code}", "unknown failure"))
        self.code, self.name, self.kernel = code, name, kernel
        text = f"{kernel}: {name} — {meaning}; x and P are unchanged"
        super().__init__(text + (f" ({detail})" if detail else ""))


class StaleLibraryError(RuntimeError):
    """The library on disk was generated from different sources than the manifest says."""


@dataclass(frozen=True)
class KernelInfo:
    """A kernel as described by the manifest (name, argument names, shapes)."""

    name: str
    inputs: tuple[tuple[str, tuple[int, int]], ...]
    outputs: tuple[tuple[str, tuple[int, int]], ...]
    carried: tuple[str, ...]
    per_step: tuple[str, ...]
    trusted: str = ""           # the run loop's trusted partner (codegen/spec.py Kernel.trusted)
    ignores: tuple[str, ...] = ()   # inputs no output but status depends on (Kernel.ignores)

    @classmethod
    def from_manifest(cls, entry: dict) -> "KernelInfo":
        def args(items):
            return tuple((a["name"], tuple(a["shape"])) for a in items)
        return cls(entry["name"], args(entry["inputs"]), args(entry["outputs"]),
                   tuple(entry["carried"]), tuple(entry["per_step"]), entry.get("trusted", ""),
                   tuple(entry.get("ignores", ())))

    @classmethod
    def from_kernel(cls, kernel: Kernel) -> "KernelInfo":
        return cls(kernel.name, tuple((a.name, a.shape) for a in kernel.inputs),
                   tuple((a.name, a.shape) for a in kernel.outputs), kernel.carried, kernel.per_step, kernel.trusted,
                   tuple(kernel.ignores()))

    @property
    def diagnosed(self) -> tuple[str, ...]:
        """Outputs a run loop's ``_run_diag`` keeps per step besides the state (codegen/c_backend/arguments.py)."""
        if not self.carried:
            return ()
        return tuple(n for n, shape in self.outputs[:-1] if n not in self.carried and shape[0] * shape[1])

    def pointer_names(self) -> list[tuple[str, bool]]:
        """(buffer name, is_output) in the C argument order (status excluded)."""
        return [(n, False) for n, _ in self.inputs] + [(n, True) for n, _ in self.outputs[:-1]]


def _check_buffer(kernel: str, name: str, buffer: np.ndarray, shape: tuple[int, int], dtype=np.float64) -> None:
    size = shape[0] * shape[1]
    if buffer.dtype != dtype or buffer.size != size or not (
            buffer.flags.f_contiguous or buffer.ndim <= 1 or min(shape) == 1):
        raise ValueError(f"{kernel}: buffer '{name}' must be {np.dtype(dtype).name} with {size} elements in "
                         "column-major order")


def manifest_precision(manifest: dict) -> str:
    """The build's casadi_real ("double" or "float") as its manifest records the codegen config."""
    extra = dict(tuple(item) for item in manifest.get("config", {}).get("extra", []))
    return extra.get("precision", "double")


def open_library(library: Path, sha256: str | None) -> ctypes.CDLL:
    """``library`` opened with ctypes, only as the very file checked: a descriptor opened without
    following a symlink, refused unless the file is this user's, hashed (given ``sha256``); the
    library the dynamic loader then maps under that name must be that file (same inode)."""
    fd = open_checked(library)
    try:
        if sha256 is not None and sha256_fd(fd) != sha256:
            raise StaleLibraryError(f"{library} does not match the SHA-256 its manifest records; it was not opened. "
                                    "Rebuild with `symkf build <model>`")
        lib = ctypes.CDLL(str(library))
        if not mapped_is(fd, library):
            raise StaleLibraryError(f"{library} was replaced while it was being opened; rebuild with "
                                    "`symkf build <model>`")
        return lib
    finally:
        os.close(fd)


class CompiledBackend:
    """The compiled library of one model, loaded with ctypes and checked against its manifest."""

    kind = "compiled"

    def __init__(self, library: Path, manifest: dict, key: str | None = None):
        """``key``: the content hash the caller computed from the model it read (default: the
        manifest's); a library with another embedded hash is refused."""
        self.manifest = manifest
        self.model = manifest["model"]
        self.library_path = library
        key = key or manifest["content_hash"]
        self.lib = open_library(library, manifest.get("library_sha256"))
        hash_fn = getattr(self.lib, f"{self.model}_content_hash")
        hash_fn.restype = ctypes.c_char_p
        embedded = hash_fn().decode()
        if embedded != manifest["content_hash"] or embedded != key:
            raise StaleLibraryError(f"{library} was generated with content hash {embedded}, the manifest "
                                    f"says {manifest['content_hash']}: rebuild with `symkf build {self.model} --force`")
        self.kernels = {k["name"]: KernelInfo.from_manifest(k) for k in manifest["kernels"]}
        #: The buffers' element type: float32 for a float build (precision="float"), else float64.
        self.dtype = np.dtype(np.float32 if manifest_precision(manifest) == "float" else np.float64)
        self._scalar = ctypes.c_float if self.dtype == np.float32 else ctypes.c_double

    @classmethod
    def from_directory(cls, directory: Path) -> "CompiledBackend":
        """The library of a build folder, opened only if its SHA-256 matches the manifest's."""
        manifest = verified_manifest(directory)
        if manifest is None:
            raise StaleLibraryError(f"{directory}: the library is missing, damaged or not the one its manifest "
                                    "records (SHA-256); it was not opened. Rebuild with `symkf build <model>`")
        return cls(directory / manifest["hashed_library"], manifest)

    @classmethod
    def from_build(cls, result: BuildResult) -> "CompiledBackend":
        """The library of a build just made or checked (:func:`symkf.codegen.build_model`): the
        manifest it carries was read and its library hashed then, so neither is done again."""
        if not result.record:
            raise StaleLibraryError(f"{result.directory}: no readable manifest; it was not opened. "
                                    "Rebuild with `symkf build <model>`")
        return cls(result.library, result.record, result.content_hash)

    def bind(self, kernel: str, buffers: dict[str, np.ndarray], entry: str = "v") -> "BoundCall":
        """``<model>_<kernel>_<entry>`` (the binding entry ``_v``, or ``unchecked_v``: no test of the
        inputs' finiteness, for a run's trusted kernel) bound to ``buffers`` by argument name."""
        info = self.kernels[kernel]
        shapes = dict(info.inputs + info.outputs)
        for name, _ in info.pointer_names():
            _check_buffer(kernel, name, buffers[name], shapes[name], self.dtype)
        pointers = (ctypes.c_void_p * max(len(info.pointer_names()), 1))(
            *[buffers[name].ctypes.data for name, _ in info.pointer_names()])
        function = getattr(self.lib, f"{self.model}_{kernel}_{entry}")
        function.argtypes = None           # a prebuilt byref needs no per-call conversion (measured
        function.restype = ctypes.c_int    # 0.39 vs 0.62 us per call with argtypes + an int address)
        return BoundCall(kernel, function, ctypes.byref(pointers), keep_alive=(pointers, buffers),
                         c_address=ctypes.cast(function, ctypes.c_void_p).value, c_args=ctypes.addressof(pointers))

    def lockstep_function(self, kernel: str):
        """``<model>_<kernel>_run_lockstep`` (codegen/c_backend/lockstep.py) if the library has it and
        this CPU can run it (its ``_lockstep_available``), else None."""
        function = getattr(self.lib, f"{self.model}_{kernel}_run_lockstep", None)
        available = getattr(self.lib, f"{self.model}_{kernel}_lockstep_available", None)
        return function if function is not None and available is not None and available() else None

    def run_function(self, kernel: str, diagnostics: bool = False):
        """``<model>_<kernel>_run`` as ``run(n_steps, *input_addresses, *hist_addresses, status_address)``
        (``diagnostics``: ``_run_diag``, whose histories are the state's, then those of
        :attr:`KernelInfo.diagnosed`).

        The C signature passes constant scalars (kappa) by value and leaves zero-size inputs out
        (:func:`symkf.codegen.c_backend.api.passing`); this adapter takes every input's buffer address,
        in manifest order, and passes each the way the C function expects it.
        """
        info = self.kernels[kernel]
        function = getattr(self.lib, f"{self.model}_{kernel}_run" + ("_diag" if diagnostics else ""))
        how = [run_passing(name, shape, info) for name, shape in info.inputs]
        histories = len(info.carried) + (len(info.diagnosed) if diagnostics else 0)
        function.argtypes = ([ctypes.c_int] + [self._scalar if h == "value" else ctypes.c_void_p
                                               for h in how if h != "omit"]
                             + [ctypes.c_void_p] * (histories + 1))
        function.restype = ctypes.c_int

        def run(n_steps: int, *addresses: int) -> int:
            inputs, outputs = addresses[:len(how)], addresses[len(how):]
            passed = [self._scalar.from_address(a).value if h == "value" else a
                      for h, a in zip(how, inputs) if h != "omit"]
            return function(n_steps, *passed, *outputs)
        return run


def run_passing(name: str, shape: tuple[int, int], info: KernelInfo) -> str:
    """How ``<kernel>_run`` takes an input: 'omit', 'value' or 'pointer' (the C writer's rule)."""
    return passing(Arg(name, shape), info, run=True)


class BoundCall(functools.partial):
    """A kernel bound to its buffers: calling it runs the kernel and returns the status code.

    For the compiled backend this is ``partial(c_function, pointer_array_address)``: one ctypes
    call with one integer argument; ``c_address`` and ``c_args`` are the addresses of the C
    function ``int f(double *const *args)`` and of its argument array (for
    :mod:`symkf.runtime.fastcall`; None on the VM backend).
    """

    def __new__(cls, kernel: str, function, *address, keep_alive=None, c_address=None, c_args=None):
        self = super().__new__(cls, function, *address)
        self.kernel, self.keep_alive = kernel, keep_alive
        self.c_address, self.c_args = c_address, c_args
        return self


def inputs_finite(info: KernelInfo, values: list[np.ndarray]) -> bool:
    """The C wrappers' input rule (codegen/c_backend/api.py), for the VM: every input finite, a
    measurement z only where its mask is > 0.5 when z and mask have one entry per component
    (kernels may rely on it: codegen/families/manifold.py tests no input itself)."""
    named = {name: np.asarray(v).reshape(-1, order="F") for (name, _), v in zip(info.inputs, values)}
    mask = named.get("mask")
    for name, value in named.items():
        if name == "z" and mask is not None and mask.size == value.size and value.size:
            value = value[mask > 0.5]
        if not np.isfinite(value).all():
            return False
    return True


class VirtualMachineBackend:
    """The same kernels evaluated by CasADi's virtual machine (no C compiler needed; slower)."""

    kind = "casadi-vm"
    #: CasADi's VM evaluates in double (``load`` refuses a float configuration on this backend).
    dtype = np.dtype(np.float64)

    def __init__(self, bundle: Bundle, reason: str = ""):
        self.model = bundle.model_name
        self.functions = {k.name: k.function for k in bundle.kernels}
        self.kernels = {k.name: KernelInfo.from_kernel(k) for k in bundle.kernels}
        self.config_extra = tuple(bundle.config.extra)       # the codegen options, as a manifest's
        if reason:
            warnings.warn(f"{reason}; evaluating '{self.model}' in CasADi's virtual machine "
                          "(same numbers, much slower)", RuntimeWarning, stacklevel=3)

    def bind(self, kernel: str, buffers: dict[str, np.ndarray], entry: str = "v") -> BoundCall:
        """``kernel`` evaluated on ``buffers`` (every ``entry`` tests the inputs here)."""
        info, function = self.kernels[kernel], self.functions[kernel]
        shapes = dict(info.inputs + info.outputs)
        for name, _ in info.pointer_names():
            _check_buffer(kernel, name, buffers[name], shapes[name])

        def evaluate() -> int:
            args = [buffers[n].reshape(s, order="F") for n, s in info.inputs]
            if not inputs_finite(info, args):
                return STATUS_NONFINITE
            results = function.call(args)
            status = int(results[-1])
            if status not in (0, STATUS_GATED):       # a gated update's outputs are written, as in C
                return status
            values = [np.asarray(r, dtype=float).reshape(-1, order="F") for r in results[:-1]]
            if not all(np.isfinite(v).all() for v in values):
                return STATUS_NONFINITE
            for (name, _), value in zip(info.outputs[:-1], values):
                buffers[name].reshape(-1, order="F")[:] = value
            return status

        return BoundCall(kernel, evaluate)

    def run_function(self, kernel: str, diagnostics: bool = False):
        return None


__all__ = ["BoundCall", "CompiledBackend", "KernelInfo", "StaleLibraryError", "SymkfError",
           "VirtualMachineBackend"]

"""The build lifecycle: generate -> compile -> install, keyed by a hash of what is generated.

``build_model(model)`` writes ``<root>/<folder>/`` = the C units (``<name>_api.c``,
``<name>_hash.c``, one ``<name>_k_<kernel>.c`` per kernel and one ``<name>_fn_<function>.c`` per
function the kernels call), ``<name>.h``, ``Makefile``, ``manifest.json`` and ``lib<name>.so``, where ``<folder>`` is the model's name for its default codegen configuration
and ``<name>-<cfg8>`` for any other, so switching options back and forth does not rebuild. The
library is compiled from exactly these units (one compiler per core), each object cached in
``<root>/.objects`` by the hash of the compiler, flags and the unit's text (the preprocessor's
output for the units that include the header), so an edit of the dynamics recompiles the
functions that evaluate the dynamics only.

The content hash covers exactly what determines the library: the model's serialized CasADi
Functions (f and every h), its description (symbols, units, sigmas, wrap flags, defaults), the
filter families and generic kernels it asks for, the codegen configuration, the source of the
codegen modules that generate it, the symkf and CasADi versions, the compiler's identity
(``cc --version``) and flags. Never file times, never other models' files: editing one model
rebuilds only that model. The check needs no generation, so an unchanged ``load`` costs well
under 0.3 s.

Nothing is loaded that this user did not build: the build root is ``$SYMKF_BUILD_DIR``, else the
source checkout's ``build/`` in a development install, else a per-user cache
(``$XDG_CACHE_HOME/symkf`` or ``~/.cache/symkf``), never the current directory, and it is refused
if other users can write to it. The manifest records the SHA-256 of the library; it is checked
before every load (a damaged or replaced library is rebuilt, never opened). The library Python
loads is its own copy with a per-build name, sharing no inode with ``lib<name>.so``.

A build happens in a staging folder moved into place when complete, under a per-folder lock
(opened without following symlinks); staging folders left by a killed build are removed by the
next one, and the compiler dies with the process that started it.
"""
from __future__ import annotations

import ctypes
import errno
import fcntl
import fnmatch
import functools
import hashlib
import importlib.metadata
import json
import os
import secrets
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import types
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path

import casadi as ca

from symkf.models import Model, get_model
from . import c_writer, families  # noqa: F401  (families register themselves on import)
from .discretize import continuous_dynamics, measurement_function
from .families.framework import FAMILIES, LONG_COMPILE, model_kernels
from .model_functions import ModelFunctions, Symbols
from .scaling import model_for
from .spec import Bundle, CodegenConfig, ConfigError, register_options

CODEGEN_DIR = Path(__file__).resolve().parent
#: Codegen modules every model's code depends on (their source is part of every content hash).
FRAMEWORK_MODULES = ("symkf.codegen.families.framework", "symkf.codegen.model_functions", "symkf.codegen.discretize",
                     "symkf.codegen.linalg", "symkf.codegen.spec", "symkf.codegen.c_writer", "symkf.codegen.build",
                     "symkf.codegen.scaling", "symkf.models.base")
#: Files of a bundle exported by ``symkf build X --out DIR`` (``{name}`` = the model's name),
#: besides the C units the manifest lists under "sources".
BUNDLE_FILES = ("{name}.h", "Makefile", "manifest.json", "lib{name}.so")


class BuildError(RuntimeError):
    """Generating or compiling a model failed; the message says what and how to fix it."""


class CompilerNotFound(BuildError):
    """No C compiler: the runtime can still evaluate the kernels in CasADi's virtual machine."""


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


# ---------------------------------------------------------------------- where builds go
def development_checkout() -> Path | None:
    """The source checkout this package runs from (an editable install), else None."""
    checkout = CODEGEN_DIR.parent
    if (checkout / "pyproject.toml").is_file() and (checkout / "models" / "base.py").is_file():
        return checkout
    return None


def build_root() -> Path:
    """``$SYMKF_BUILD_DIR``, else the checkout's ``build/`` (development install), else the per-user
    cache ``$XDG_CACHE_HOME/symkf`` (default ``~/.cache/symkf``). Never the current directory."""
    env = os.environ.get("SYMKF_BUILD_DIR")
    if env:
        return Path(env).expanduser().resolve()
    checkout = development_checkout()
    if checkout is not None:
        return checkout / "build"
    cache = os.environ.get("XDG_CACHE_HOME", "")
    base = Path(cache) if cache and Path(cache).is_absolute() else Path.home() / ".cache"
    return base / "symkf"


def private_root() -> Path:
    """:func:`build_root`, created if needed, refused if another user owns it or can write to it."""
    root = build_root()
    try:
        root.mkdir(parents=True, exist_ok=True, mode=0o755)
        info = root.stat()
    except OSError as exc:
        raise BuildError(f"build folder {root}: {exc.strerror or exc}; set SYMKF_BUILD_DIR to a folder you own") from None
    if info.st_uid != os.geteuid() or info.st_mode & 0o022:
        raise BuildError(f"build folder {root} is writable by other users or not yours (mode {info.st_mode & 0o777:o}); "
                         f"a library there could be replaced: `chmod go-w {root}` or set SYMKF_BUILD_DIR")
    return root


def folder_name(model: Model, config: CodegenConfig) -> str:
    """``<name>`` for the model's default configuration, ``<name>-<cfg8>`` for any other."""
    if config == default_config(model):
        return model.name
    text = json.dumps(asdict(config), sort_keys=True, default=str)
    return f"{model.name}-{hashlib.sha256(text.encode()).hexdigest()[:8]}"


# ---------------------------------------------------------------------- configuration and hash
def default_config(model: Model) -> CodegenConfig:
    return CodegenConfig().with_overrides(**model.codegen_defaults)


def make_config(model, **overrides) -> CodegenConfig:
    """The model's codegen defaults (``Model.codegen_defaults``) with overrides applied."""
    model = get_model(model)
    return CodegenConfig().with_overrides(**{**model.codegen_defaults, **overrides})


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


def _source_digest(module: types.ModuleType) -> str:
    return _file_digest(module.__name__, getattr(module, "__file__", None) or "")


@functools.lru_cache(maxsize=None)
def _file_digest(name: str, path: str) -> str:
    """SHA-256 of a module's source, read once per process (the code this process generates with)."""
    try:
        return hashlib.sha256(Path(path).read_bytes()).hexdigest()
    except OSError:
        return "no-source"


def codegen_modules(model: Model) -> list[types.ModuleType]:
    """The framework modules plus each filter family the model asks for and the symkf modules
    that family uses (e.g. the quaternion filters read constants from models/attitude.py)."""
    modules = {name: sys.modules[name] for name in FRAMEWORK_MODULES}
    for family in model.filters:
        if family not in FAMILIES:
            raise BuildError(f"model '{model.name}' asks for filter family '{family}'; known: {sorted(FAMILIES)}")
        module = sys.modules[FAMILIES[family].__module__]
        modules[module.__name__] = module
        for value in vars(module).values():
            owner = value if isinstance(value, types.ModuleType) else sys.modules.get(getattr(value, "__module__", "") or "")
            if isinstance(owner, types.ModuleType) and owner.__name__.startswith("symkf."):
                modules[owner.__name__] = owner
    return [modules[name] for name in sorted(modules)]


def _symkf_version() -> str:
    try:
        return importlib.metadata.version("symkf")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


def generated_hash(model: Model, config: CodegenConfig) -> str:
    """Hash of what is generated, independent of the compiler (no generation needed)."""
    model = model_for(model, config)
    digest = hashlib.sha256()
    digest.update(continuous_dynamics(model).serialize().encode())
    for name in model.measurements:
        digest.update(measurement_function(model, name).serialize().encode())
    facts = {"description": model.describe(), "filters": list(model.filters),
             "generic_kernels": list(model.generic_kernels), "config": asdict(config),
             "codegen": {m.__name__: _source_digest(m) for m in codegen_modules(model)},
             "symkf": _symkf_version(), "casadi": ca.__version__}
    digest.update(json.dumps(facts, sort_keys=True, default=str).encode())
    return digest.hexdigest()


def content_hash(model: Model, config: CodegenConfig, cc: str, generated: str | None = None) -> str:
    """Hash of everything that determines the library: what is generated + compiler + flags."""
    generated = generated or generated_hash(model, config)
    text = json.dumps({"generated": generated, "cc": compiler_identity(cc),
                       "flags": c_writer.STRICT_FLAGS, "optimization": config.optimization}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:32]


# ---------------------------------------------------------------------- generate
def generate(model, config: CodegenConfig | None = None) -> Bundle:
    """Model -> kernels (CasADi Functions) for every filter family the model asks for."""
    model = get_model(model)
    return _generate(model, config or default_config(model))


def _generate(model: Model, config: CodegenConfig, on_part=None) -> Bundle:
    """:func:`generate` of a model already validated (by :func:`build_model`). The kernels are made
    in parts: the model's own (f, f_d, F, h, H), then each filter family's, in the model's order.
    ``on_part(index, part)``, if given, receives each part's bundle as soon as it is made (a build
    starts compiling its units while the next part is generated); the families with the longest
    compile (:data:`~symkf.codegen.families.framework.LONG_COMPILE`) are made first."""
    model = model_for(model, config)
    for family in model.filters:
        if family not in FAMILIES:
            raise BuildError(f"model '{model.name}' asks for filter family '{family}'; known: {sorted(FAMILIES)}")
    symbols, functions = Symbols(model), ModelFunctions(model, config)
    own = model_kernels(model, symbols, functions)
    if on_part is not None:
        on_part(0, Bundle(model.name, list(own), config, model.describe()))
    made = {}
    for family in sorted(model.filters, key=lambda name: name not in LONG_COMPILE):    # stable: else the model's order
        made[family] = FAMILIES[family](model, symbols, functions)
        if on_part is not None:
            on_part(1 + model.filters.index(family), Bundle(model.name, list(made[family].kernels), config,
                                                             model.describe()))
    kernels = own + [k for family in model.filters for k in made[family].kernels]
    filters = [f for family in model.filters for f in made[family].filters]
    _check_c_names(model.name, kernels)
    parts = (len(own),) + tuple(len(made[family].kernels) for family in model.filters)
    return Bundle(model.name, kernels, config, model.describe(), filters, parts)


def _check_c_names(model: str, kernels) -> None:
    """Every generated C function name once (a safety net behind Model.validate's naming rule)."""
    seen = {"content_hash": "the content hash"}
    for kernel in kernels:
        for name in (kernel.name, f"{kernel.name}_v") + ((f"{kernel.name}_run",) if kernel.runnable else ()):
            if name in seen:
                raise BuildError(f"model '{model}': C function {model}_{name} would come from both {seen[name]} "
                                 f"and kernel '{kernel.name}'; rename the measurement")
            seen[name] = f"kernel '{kernel.name}'"


# ---------------------------------------------------------------------- up-to-date checks
def sha256_file(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def read_manifest(directory: Path) -> dict | None:
    try:
        manifest = json.loads((directory / "manifest.json").read_text())
        manifest["content_hash"], manifest["library_sha256"], manifest["hashed_library"]
        return manifest
    except (OSError, ValueError, KeyError, TypeError):
        return None


def verified_library(directory: Path, manifest: dict) -> Path | None:
    """The manifest's library if its SHA-256 matches the recorded one, else None."""
    name = manifest["hashed_library"]
    if not isinstance(name, str) or Path(name).name != name or not name.endswith(".so"):
        return None
    path = directory / name
    try:
        ok = path.is_file() and not path.is_symlink() and sha256_file(path) == manifest["library_sha256"]
    except OSError:
        return None
    return path if ok else None


def is_up_to_date(directory: Path, key: str, field: str = "content_hash") -> bool:
    manifest = read_manifest(directory)
    return manifest is not None and manifest.get(field) == key and verified_library(directory, manifest) is not None


# ---------------------------------------------------------------------- build
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
    config = CodegenConfig().with_overrides(**{**model.codegen_defaults, **overrides})
    unit_optimization(config)                                   # a bad per-unit option: refused before any work
    timings = {}
    root = private_root()
    directory = root / folder_name(model, config)
    generated = generated_hash(model, config)
    try:
        cc = compiler()
    except CompilerNotFound:
        if not force and is_up_to_date(directory, generated, "generated_hash"):
            return _result(model.name, directory, True, start)
        raise
    key = content_hash(model, config, cc, generated)
    timings["model"] = time.perf_counter() - start
    if not force and is_up_to_date(directory, key):
        return _result(model.name, directory, True, start)
    with _lock(root, directory.name):
        if not force and is_up_to_date(directory, key):      # another process built it meanwhile
            return _result(model.name, directory, True, start)
        _remove_stale(root, directory.name)
        staging = Path(tempfile.mkdtemp(prefix=f".{directory.name}.tmp-", dir=root))
        try:
            with UnitCompiler(staging, cc, config, f"{model.name}.h") as units:
                mark, per_part = time.perf_counter(), {}      # each part's units compile while the next part generates

                def on_part(index: int, part: Bundle) -> None:
                    per_part[index] = c_writer.part_units(part)
                    units.add(per_part[index])
                bundle = _generate(model, config, on_part)
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
    return _result(model.name, directory, False, start, timings, compiled)


def _result(name: str, directory: Path, up_to_date: bool, start: float, timings: dict | None = None,
            compiled: list[str] = ()) -> BuildResult:
    manifest = read_manifest(directory) or {}
    return BuildResult(name, directory, directory / manifest.get("hashed_library", f"lib{name}.so"),
                       directory / "manifest.json", manifest.get("content_hash", ""), up_to_date,
                       time.perf_counter() - start, dict(timings or {}), tuple(compiled))


def write_bundle(bundle: Bundle, directory: Path, key: str, generated: str, cc: str,
                 units: UnitCompiler | None = None, per_part: list[dict[str, str]] | None = None) -> None:
    """Write the translation units (through ``units``, which starts compiling them), the header,
    the Makefile and a provisional manifest.json (no library yet; ``sources`` lists the units,
    the API unit first). ``per_part``: the units of each part of the bundle, if already made."""
    name = bundle.model_name
    sources = c_writer.units(bundle, key, per_part)
    if units is not None:
        units.add(sources)
    else:
        for file, text in sources.items():
            (directory / file).write_text(text)
    (directory / f"{name}.h").write_text(c_writer.header(bundle, key, cc, " ".join(compile_flags(bundle.config))))
    own = {file: flags for file in sources if (flags := unit_optimization(bundle.config, file)) != bundle.config.optimization}
    (directory / "Makefile").write_text(c_writer.makefile(name, bundle.config.optimization, list(sources), own))
    manifest = {"model": name, "content_hash": key, "generated_hash": generated,
                "symkf_version": _symkf_version(), "casadi_version": ca.__version__,
                "compiler": cc, "compiler_identity": compiler_identity(cc), "flags": c_writer.STRICT_FLAGS,
                "optimization": bundle.config.optimization, "unit_optimization": own, "config": asdict(bundle.config),
                "description": bundle.description, "library": f"lib{name}.so", "sources": list(sources),
                "kernels": [k.as_dict() for k in bundle.kernels],
                "filters": [f.as_dict() for f in bundle.filters]}
    (directory / "manifest.json").write_text(json.dumps(manifest, indent=1))


def compile_flags(config: CodegenConfig, unit: str = "") -> list[str]:
    """Flags of a unit (:func:`unit_optimization`), in the library and in the bundle's Makefile alike."""
    return (c_writer.STRICT_FLAGS.split() + unit_optimization(config, unit).split() + ["-fPIC"]
            + c_writer.precision_flags(config))


register_options("unit_optimization")


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
        returncode, _ = run_compiler(cc.split() + c_writer.STACK_FLAGS.split() + ["-c", "-o", "probe.o", "probe.c"],
                                     Path(tmp))
        return returncode == 0 and (Path(tmp) / "probe.ci").is_file()


def compile_bundle(directory: Path, name: str, cc: str, config: CodegenConfig,
                   units: UnitCompiler | None = None) -> list[str]:
    """Compile the manifest's units in parallel (:class:`UnitCompiler`: one compiler per core; a
    unit whose text, compiler and flags match a cached object is not recompiled; ``units``: the
    compiler the build already started units with), fill the header's stack figures from the
    compiler's call graphs of those same compiles, link lib<name>.so, copy it to the per-build name
    Python loads and record that copy's SHA-256. Returns the units compiled."""
    manifest = json.loads((directory / "manifest.json").read_text())
    if units is None:
        with UnitCompiler(directory, cc, config, f"{name}.h") as units:
            units.add({file: (directory / file).read_text() for file in manifest["sources"]})
            return compile_bundle(directory, name, cc, config, units)
    objects, compiled = units.finish(manifest["sources"])
    graphs = "".join(obj.with_suffix(".ci").read_text() for obj in objects) if units.stack else None
    header = directory / f"{name}.h"
    header.write_text(c_writer.fill_stack(header.read_text(), c_writer.stack_usage(graphs) if units.stack else None))
    cmd = cc.split() + ["-shared", "-o", f"lib{name}.so"] + [o.name for o in objects] + ["-lm"]
    returncode, stderr = run_compiler(cmd, directory)
    if returncode != 0:
        raise BuildError(f"linking lib{name}.so failed ({' '.join(cmd)}):\n{stderr[-4000:]}")
    for obj in objects:
        for leftover in (obj, obj.with_suffix(".ci"), obj.with_suffix(".su")):
            leftover.unlink(missing_ok=True)
    loaded = f"lib{name}.{manifest['content_hash'][:12]}.{secrets.token_hex(4)}.so"
    shutil.copyfile(directory / f"lib{name}.so", directory / loaded)        # a copy, never a hard link
    manifest.update(hashed_library=loaded, library_sha256=sha256_file(directory / loaded))
    (directory / "manifest.json").write_text(json.dumps(manifest, indent=1))
    return compiled


@dataclass
class _Unit:
    text: str
    cached: Path | None = None           # its object cache entry (None: not keyed yet)
    job: int | None = None               # its compile in the pool (None: the object came from the cache)


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

    def __init__(self, directory: Path, cc: str, config: CodegenConfig, header: str, jobs: int | None = None):
        self.directory, self.cc, self.config, self.header = directory, cc, config, header
        self.stack = measures_stack(cc)
        self.suffixes = (".o", ".ci") if self.stack else (".o",)
        self.cache = directory.parent / ".objects"
        self.cache.mkdir(exist_ok=True)
        self.jobs = max(1, jobs or os.cpu_count() or 1)
        self.pool = CompilerPool(directory, max(1, self.jobs - 1), cores=self.jobs)     # this process is generating
        self.units: dict[str, _Unit] = {}

    def __enter__(self) -> "UnitCompiler":
        return self

    def __exit__(self, kind, value, traceback) -> None:
        self.pool.__exit__(kind, value, traceback)

    def flags(self, file: str) -> list[str]:
        return compile_flags(self.config, file) + (c_writer.STACK_FLAGS.split() if self.stack else [])

    def add(self, texts: dict[str, str]) -> None:
        """Write these units and start compiling each one whose object is not cached; a unit
        written before with another text is cancelled and restarted. A unit that includes the
        header is keyed (and started) by :meth:`finish`, once the header is written."""
        for file, text in sorted(texts.items(), key=lambda item: -len(item[1])):
            unit = self.units.get(file)
            if unit is not None and unit.text == text:
                continue
            if unit is not None and unit.job is not None:
                self.pool.cancel(unit.job)
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
        if not _reuse(unit.cached, obj, self.suffixes):
            unit.job = self.pool.submit(self.cc.split() + self.flags(file) + ["-c", "-o", obj.name, file],
                                        priority=len(unit.text))      # the longest compile first

    def finish(self, sources: list[str]) -> tuple[list[Path], list[str]]:
        """Start the units that include the header, wait for every compile and cache the new
        objects. Returns the objects of ``sources`` (in order) and the units compiled; units added
        but not in ``sources`` (early ones the final code does not have) are removed."""
        self.pool.jobs = self.jobs                                       # done generating: every core compiles
        for file in set(self.units) - set(sources):
            unit = self.units.pop(file)
            if unit.job is not None:
                self.pool.cancel(unit.job)
            for suffix in (".c", ".o", ".ci", ".su"):
                (self.directory / (file[:-2] + suffix)).unlink(missing_ok=True)
        waiting = [file for file in sources if self.units[file].cached is None]
        commands = [self.cc.split() + compile_flags(self.config, file) + ["-E", "-o", file[:-2] + ".i", file]
                    for file in waiting]
        for cmd, (returncode, stderr) in zip(commands, run_compilers(commands, self.directory)):
            if returncode != 0:
                raise BuildError(f"preprocessing {cmd[-1]} failed ({' '.join(cmd)}):\n{stderr[-4000:]}")
        for file in waiting:
            self._start(file, (self.directory / (file[:-2] + ".i")).read_text())
            (self.directory / (file[:-2] + ".i")).unlink()
        results = self.pool.wait()
        compiled = [file for file in sources if self.units[file].job is not None]
        for file in compiled:
            returncode, stderr = results[self.units[file].job]
            if returncode != 0:
                cmd = self.cc.split() + self.flags(file) + ["-c", file]
                raise BuildError(f"compiling {file} failed ({' '.join(cmd)}):\n{stderr[-4000:]}")
        for file in compiled:
            _store(self.units[file].cached, self.directory / (file[:-2] + ".o"), self.suffixes)
        _prune(self.cache, keep=400)
        return [self.directory / (file[:-2] + ".o") for file in sources], compiled


def _reuse(cached: Path, obj: Path, suffixes: tuple[str, ...]) -> bool:
    """Copy a cached entry next to the unit if its sums match the copies; False (compile) otherwise."""
    try:
        sums = json.loads(cached.with_suffix(".sum").read_text())
        for suffix in suffixes:
            shutil.copyfile(cached.with_suffix(suffix), obj.with_suffix(suffix))
            if sha256_file(obj.with_suffix(suffix)) != sums[suffix]:
                return False
        return True
    except (OSError, ValueError, KeyError, TypeError):
        return False


def _store(cached: Path, obj: Path, suffixes: tuple[str, ...]) -> None:
    """Add a compiled unit to the cache: its files, then (atomically, last) their sums."""
    sums = {}
    for suffix in suffixes:
        temporary = cached.parent / f".{cached.name}{suffix}.{secrets.token_hex(4)}"
        shutil.copyfile(obj.with_suffix(suffix), temporary)
        sums[suffix] = sha256_file(temporary)
        os.replace(temporary, cached.with_suffix(suffix))
    temporary = cached.parent / f".{cached.name}.sum.{secrets.token_hex(4)}"
    temporary.write_text(json.dumps(sums))
    os.replace(temporary, cached.with_suffix(".sum"))


def _prune(cache: Path, keep: int) -> None:
    """Keep the ``keep`` most recently written cache entries (object, call graph, sums)."""
    entries = sorted(cache.glob("*.sum"), key=lambda p: p.stat().st_mtime, reverse=True)
    for path in entries[keep:]:
        for suffix in (".sum", ".o", ".ci"):
            path.with_suffix(suffix).unlink(missing_ok=True)


#: The compiler runs under a shell that kills its whole process group (cc and its cc1, as, ld)
#: when it receives SIGTERM, which the kernel sends when the building process dies (any signal).
_GROUP_GUARD = ["/bin/sh", "-c", 'trap "kill -KILL 0" TERM; "$@" & wait $!', "symkf-cc"]


def _term_with_parent() -> None:
    """In the child: SIGTERM when the parent dies (Linux PR_SET_PDEATHSIG; kept across exec)."""
    try:
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)
    except (AttributeError, OSError):
        pass


@functools.lru_cache(maxsize=1)
def _pdeathsig_wrapper() -> tuple[str, ...]:
    """``setpriv --pdeathsig TERM --`` if util-linux's setpriv has that option (2.33+), else ().
    It sets what :func:`_term_with_parent` sets, from a program of its own: without a Python
    ``preexec_fn`` the compiler is started by vfork, not by a fork of this (large) process,
    about 2 ms instead of 10-20 per unit on the build's serial path."""
    setpriv = shutil.which("setpriv")
    if setpriv is None:
        return ()
    try:
        ok = subprocess.run([setpriv, "--pdeathsig", "TERM", "--", "true"], capture_output=True, timeout=10).returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        ok = False
    return (setpriv, "--pdeathsig", "TERM", "--") if ok else ()


def _spawn(cmd: list[str], cwd: Path, stderr) -> subprocess.Popen:
    """The command in its own session and process group, under the guard shell that kills the
    group when this process dies (SIGTERM from PR_SET_PDEATHSIG, set by setpriv or in the child)."""
    linux = sys.platform.startswith("linux")
    wrapper = list(_pdeathsig_wrapper()) if linux else []
    return subprocess.Popen(wrapper + (_GROUP_GUARD if linux else []) + cmd, cwd=cwd, stdout=subprocess.DEVNULL,
                            stderr=stderr, start_new_session=True,
                            preexec_fn=_term_with_parent if linux and not wrapper else None)


def run_compiler(cmd: list[str], cwd: Path) -> tuple[int, str]:
    """Run one compiler command (see :func:`run_compilers`)."""
    return run_compilers([cmd], cwd)[0]


def run_compilers(cmds: list[list[str]], cwd: Path, jobs: int | None = None) -> list[tuple[int, str]]:
    """Run compiler commands, ``jobs`` at a time (default: one per core), each in its own process
    group that dies with this process; on any exception here (Ctrl-C) every group is killed.
    Returns (return code, stderr) per command."""
    with CompilerPool(cwd, jobs) as pool:
        indices = [pool.submit(cmd) for cmd in cmds]
        results = pool.wait()
    return [results[i] for i in indices]


class CompilerPool:
    """Compiler commands run ``jobs`` at a time (default: one per core) in the background while
    this process goes on: each in its own process group that dies with this process, started when
    submitted or at the next :meth:`poll` (a builder polls between its steps); leaving the ``with``
    block on an exception (Ctrl-C) kills every group still running. Queued commands start highest
    priority first, and one of higher priority than every running command starts at once if a
    core is left (``cores``, default: all): the longest compile never waits behind a shorter one."""

    def __init__(self, cwd: Path, jobs: int | None = None, cores: int | None = None):
        self.cwd, self.jobs = cwd, max(1, jobs or os.cpu_count() or 1)
        self.cores = max(self.jobs, cores or os.cpu_count() or 1)
        self.pending: list[tuple[int, list[str]]] = []
        self.running: dict[int, tuple[subprocess.Popen, object]] = {}
        self.results: dict[int, tuple[int, str]] = {}
        self.priority: dict[int, float] = {}
        self.submitted = 0

    def __enter__(self) -> "CompilerPool":
        return self

    def __exit__(self, kind, value, traceback) -> None:
        if kind is not None:
            for index in list(self.running):
                self.cancel(index)

    def submit(self, cmd: list[str], priority: float = 0) -> int:
        """Queue a command (started at once if a slot is free; queued ones start highest
        ``priority`` first, in order of submission among equals); returns its index."""
        self.pending.append((self.submitted, cmd))
        self.priority[self.submitted] = priority
        self.pending.sort(key=lambda item: -self.priority[item[0]])
        self.submitted += 1
        self.poll()
        return self.submitted - 1

    def poll(self) -> None:
        """Collect finished commands and start queued ones in the free slots."""
        for index, (proc, log) in list(self.running.items()):
            if proc.poll() is not None:
                log.seek(0)
                self.results[index] = (proc.returncode, log.read())
                log.close()
                del self.running[index]
        while self.pending and (len(self.running) < self.jobs or self._outranks_running()):
            index, cmd = self.pending.pop(0)
            log = tempfile.TemporaryFile(mode="w+")
            self.running[index] = (_spawn(cmd, self.cwd, log), log)

    def _outranks_running(self) -> bool:
        """The next queued command has a higher priority than every running one, and a core is free."""
        first = self.priority[self.pending[0][0]]
        return len(self.running) < self.cores and all(first > self.priority[index] for index in self.running)

    def cancel(self, index: int) -> None:
        """Drop a queued command, or kill a running one (its process group) and wait for it."""
        self.pending = [item for item in self.pending if item[0] != index]
        if index in self.running:
            proc, log = self.running.pop(index)
            try:
                os.killpg(proc.pid, signal.SIGKILL)
            except OSError:
                pass
            proc.wait()
            log.close()
        self.results[index] = (-signal.SIGKILL, "cancelled")

    def wait(self) -> dict[int, tuple[int, str]]:
        """Wait for every submitted command; (return code, stderr) by index."""
        self.poll()
        while self.pending or self.running:
            time.sleep(0.005)
            self.poll()
        return self.results


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

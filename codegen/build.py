"""The build lifecycle: generate -> compile -> install, keyed by a content hash.

``build_model(name)`` writes ``build/<name>/`` = ``<name>.c``, ``<name>.h``, ``Makefile``,
``manifest.json`` and ``lib<name>.so``. The content hash covers every source file of
``models/`` and ``codegen/``, the codegen config, the CasADi version and the compiler command, so
an edit anywhere in the chain rebuilds; an unchanged build is detected from the manifest alone in
milliseconds. A build happens in a temporary folder and is moved into place only when complete,
under a file lock, so neither a crash nor two concurrent builds leave a half-written bundle that
gets loaded; the loader also checks the library's own embedded hash.
"""
from __future__ import annotations

import fcntl
import hashlib
import json
import os
import shutil
import subprocess
import tempfile
import time
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path

import casadi as ca

from symkf.models import get_model, model_module
from . import c_writer, families  # noqa: F401  (families register themselves on import)
from .kernels import FAMILIES, ModelFunctions, Symbols, model_kernels
from .spec import Bundle, CodegenConfig

CODEGEN_DIR = Path(__file__).resolve().parent
MODELS_DIR = Path(model_module.__code__.co_filename).resolve().parent  # models/


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


def build_root() -> Path:
    """``$SYMKF_BUILD_DIR``, else ``build/`` of the source checkout, else ``./build``."""
    env = os.environ.get("SYMKF_BUILD_DIR")
    if env:
        return Path(env).resolve()
    checkout = CODEGEN_DIR.parent
    if (checkout / "pyproject.toml").exists():
        return checkout / "build"
    return Path.cwd() / "build"


def compiler() -> str:
    """The C compiler command ($CC or cc); raises CompilerNotFound with a one-line message."""
    cc = os.environ.get("CC", "cc")
    if shutil.which(cc.split()[0]) is None:
        raise CompilerNotFound(f"no C compiler found ('{cc}'): install gcc or clang, or set CC")
    return cc


def make_config(name: str, **overrides) -> CodegenConfig:
    """The model's codegen defaults (``Model.codegen_defaults``) with overrides applied."""
    model = get_model(name)
    return CodegenConfig().with_overrides(**{**model.codegen_defaults, **overrides})


def generate(name: str, config: CodegenConfig | None = None) -> Bundle:
    """Model -> kernels (CasADi Functions) for every filter family the model asks for."""
    model = get_model(name)
    config = config or CodegenConfig().with_overrides(**model.codegen_defaults)
    symbols, functions = Symbols(model), ModelFunctions(model, config)
    kernels = model_kernels(model, symbols, functions)
    for family in model.filters:
        if family not in FAMILIES:
            raise BuildError(f"model '{name}' asks for filter family '{family}'; known: {sorted(FAMILIES)}")
        kernels += FAMILIES[family](model, symbols, functions)
    return Bundle(name, kernels, config, model.describe())


def content_hash(name: str, config: CodegenConfig, cc: str) -> str:
    """Hash of everything that determines the generated library."""
    digest = hashlib.sha256()
    for folder in (MODELS_DIR, CODEGEN_DIR):
        for path in sorted(folder.rglob("*.py")):
            digest.update(path.relative_to(folder.parent).as_posix().encode())
            digest.update(path.read_bytes())
    digest.update(json.dumps({"model": name, "config": asdict(config), "casadi": ca.__version__,
                              "cc": cc, "flags": c_writer.STRICT_FLAGS}, sort_keys=True, default=str).encode())
    return digest.hexdigest()[:32]


def hashed_library(directory: Path, name: str, key: str) -> Path:
    """The per-hash copy the runtime loads (so a rebuilt library is never shadowed by dlopen's cache)."""
    return directory / f"lib{name}.{key[:16]}.so"


def is_up_to_date(directory: Path, name: str, key: str) -> bool:
    manifest = directory / "manifest.json"
    try:
        recorded = json.loads(manifest.read_text())["content_hash"]
    except (OSError, ValueError, KeyError):
        return False
    return recorded == key and hashed_library(directory, name, key).exists()


@contextmanager
def _lock(root: Path, name: str):
    root.mkdir(parents=True, exist_ok=True)
    with open(root / f".{name}.lock", "w") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def build_model(name: str, force: bool = False, **overrides) -> BuildResult:
    """Generate and compile ``build/<name>/`` unless it is already up to date."""
    start = time.perf_counter()
    cc = compiler()
    config = make_config(name, **overrides)
    key = content_hash(name, config, cc)
    root = build_root()
    directory = root / name
    if not force and is_up_to_date(directory, name, key):
        return _result(name, directory, key, True, start)
    with _lock(root, name):
        if not force and is_up_to_date(directory, name, key):   # another process built it meanwhile
            return _result(name, directory, key, True, start)
        staging = Path(tempfile.mkdtemp(prefix=f".{name}.tmp-", dir=root))
        try:
            bundle = generate(name, config)
            write_bundle(bundle, staging, key)
            compile_bundle(staging, name, cc, config)
            _install(staging, directory)
        except BaseException:
            shutil.rmtree(staging, ignore_errors=True)
            raise
    return _result(name, directory, key, False, start)


def _result(name: str, directory: Path, key: str, up_to_date: bool, start: float) -> BuildResult:
    return BuildResult(name, directory, hashed_library(directory, name, key), directory / "manifest.json",
                       key, up_to_date, time.perf_counter() - start)


def write_bundle(bundle: Bundle, directory: Path, key: str) -> None:
    """Write the .c, .h, Makefile and manifest.json of a bundle into ``directory``."""
    name = bundle.model_name
    code = c_writer.casadi_source(bundle)
    (directory / f"{name}.c").write_text(c_writer.source(bundle, key, code))
    (directory / f"{name}.h").write_text(c_writer.header(bundle, key))
    (directory / "Makefile").write_text(c_writer.makefile(name, bundle.config.optimization))
    manifest = {"model": name, "content_hash": key, "casadi_version": ca.__version__,
                "compiler": os.environ.get("CC", "cc"), "flags": c_writer.STRICT_FLAGS,
                "optimization": bundle.config.optimization, "config": asdict(bundle.config),
                "description": bundle.description,
                "library": f"lib{name}.so", "hashed_library": hashed_library(directory, name, key).name,
                "kernels": [k.as_dict() for k in bundle.kernels]}
    (directory / "manifest.json").write_text(json.dumps(manifest, indent=1))


def compile_bundle(directory: Path, name: str, cc: str, config: CodegenConfig) -> None:
    """Compile lib<name>.so with the strict flags; errors name the compiler output."""
    cmd = cc.split() + c_writer.STRICT_FLAGS.split() + config.optimization.split() + [
        "-fPIC", "-shared", "-o", f"lib{name}.so", f"{name}.c", "-lm"]
    proc = subprocess.run(cmd, cwd=directory, capture_output=True, text=True)
    if proc.returncode != 0:
        raise BuildError(f"compiling build/{name}/{name}.c failed ({' '.join(cmd)}):\n{proc.stderr[-4000:]}")
    key = json.loads((directory / "manifest.json").read_text())["content_hash"]
    os.link(directory / f"lib{name}.so", hashed_library(directory, name, key))


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

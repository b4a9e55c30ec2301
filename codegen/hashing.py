"""The hashes that key a build: of what is generated, and of that plus the compiler and flags.

The content hash covers exactly what determines the library: the model's serialized CasADi
Functions (f and every h), its description (symbols, units, sigmas, wrap flags, defaults), the
filter families and generic kernels it asks for, the codegen configuration, the source of the
codegen modules that generate it, the symkf and CasADi versions, the compiler's identity
(``cc --version``) and flags. Never file times, never other models' files: editing one model
rebuilds only that model. The check needs no generation, so an unchanged ``load`` costs well
under 0.3 s.
"""
from __future__ import annotations

import functools
import hashlib
import importlib.metadata
import json
import sys
import types
from dataclasses import asdict
from pathlib import Path

import casadi as ca

from symkf.models import Model
from .c_backend import makefile as c_makefile
from .c_backend.template_util import templates_digest
from .compilation import compiler_identity
from .discretize import continuous_dynamics, measurement_function
from .errors import BuildError
from .families.framework import FAMILIES
from .scaling import model_for
from .spec import CodegenConfig

#: Codegen modules every model's code depends on (their source is part of every content hash).
#: Every module of codegen/ but the families (those a model asks for are added by
#: :func:`codegen_modules`); tests/codegen/test_build_lifecycle.py checks that none is missing.
FRAMEWORK_MODULES = ("symkf.codegen.build_folders", "symkf.codegen.c_backend.api", "symkf.codegen.c_backend.arguments",
                     "symkf.codegen.c_backend.casadi_text",
                     "symkf.codegen.c_backend.flatten", "symkf.codegen.c_backend.header", "symkf.codegen.c_backend.lanes",
                     "symkf.codegen.c_backend.lockstep", "symkf.codegen.c_backend.lockstep_units", "symkf.codegen.c_backend.makefile", "symkf.codegen.c_backend.vector_c",
                     "symkf.codegen.c_backend.multi_loop", "symkf.codegen.c_backend.names",
                     "symkf.codegen.c_backend.smooth_loop", "symkf.codegen.c_backend.smooth_lockstep",
                     "symkf.codegen.c_backend.stack", "symkf.codegen.c_backend.template_util", "symkf.codegen.c_backend.units",
                     "symkf.codegen.compilation",
                     "symkf.codegen.compiler_pool", "symkf.codegen.discretize", "symkf.codegen.errors", "symkf.codegen.export",
                     "symkf.codegen.float_check",
                     "symkf.codegen.generation", "symkf.codegen.hashing", "symkf.codegen.families.framework",
                     "symkf.codegen.model_functions",
                     "symkf.codegen.lifecycle", "symkf.codegen.linalg", "symkf.codegen.manifest", "symkf.codegen.progress",
                     "symkf.codegen.safe_files", "symkf.codegen.scaling", "symkf.codegen.spec",
                     "symkf.codegen.square_root", "symkf.models.base", "symkf.models.estimation")


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


def symkf_version() -> str:
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
    for name in sorted(model.functions):
        digest.update(name.encode() + model.functions[name].serialize().encode())
    facts = {"description": model.describe(), "filters": list(model.filters),
             "generic_kernels": list(model.generic_kernels), "config": asdict(config),
             "codegen": {m.__name__: _source_digest(m) for m in codegen_modules(model)},
             "templates": templates_digest(),
             "symkf": symkf_version(), "casadi": ca.__version__}
    digest.update(json.dumps(facts, sort_keys=True, default=str).encode())
    return digest.hexdigest()


def content_hash(model: Model, config: CodegenConfig, cc: str, generated: str | None = None) -> str:
    """Hash of everything that determines the library: what is generated + compiler + flags."""
    generated = generated or generated_hash(model, config)
    text = json.dumps({"generated": generated, "cc": compiler_identity(cc),
                       "flags": c_makefile.STRICT_FLAGS, "optimization": config.optimization}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:32]

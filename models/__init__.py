"""Symbolic models (CasADi SX only). A model is any Python file or module whose ``build()`` returns
a :class:`Model`; :func:`get_model` finds, executes and validates one.

    get_model("launcher")               # a paper model of this package (models/launcher.py)
    get_model("path/to/tracker.py")     # a file anywhere (ends in .py or contains a path separator)
    get_model("mypkg.tracker")          # an importable module, by dotted name
    get_model(module) / get_model(model)

A model's file is read and executed afresh on every call, never served from Python's module cache
(``sys.modules``) nor from cached bytecode, so an edit made in a running notebook gives the new
equations on the next build or load.
"""
from __future__ import annotations

import ast
import importlib
import importlib.util
import io
import itertools
import math
import os
import re
import sys
import tokenize
import traceback
import types
from pathlib import Path

from .base import Measurement, Model, Variable
from .errors import ModelError

__all__ = ["Measurement", "Model", "ModelError", "Variable", "get_model", "PAPER_MODELS"]

MODELS_DIR = Path(__file__).resolve().parent
#: Short names of the paper models shipped in this package.
PAPER_MODELS = ("launcher", "attitude", "geo_satellite", "marg")
_fresh_names = itertools.count()


def get_model(spec) -> Model:
    """Build and validate the model named by ``spec`` (a Model, a module, a short name, a path or a
    dotted module name); its file is executed afresh."""
    if isinstance(spec, Model):
        return spec.validate()
    if isinstance(spec, types.ModuleType):
        return _from_module(spec)
    if isinstance(spec, os.PathLike):
        return _from_file(Path(spec), package=None)
    if not isinstance(spec, str) or not spec:
        raise ModelError(f"a model is a Model, a module, a file path or a module name, not {type(spec).__name__}")
    if spec.endswith(".py") or os.sep in spec or "/" in spec:
        return _from_file(Path(spec), package=None)
    if spec.isidentifier() and (MODELS_DIR / f"{spec}.py").is_file():
        return _from_file(MODELS_DIR / f"{spec}.py", package=__name__, display=spec)
    return _from_module_name(spec)


def _from_module(module: types.ModuleType) -> Model:
    """A module object: its source file executed afresh (a module with no .py file: its build())."""
    path = getattr(module, "__file__", None)
    if path and path.endswith(".py") and Path(path).is_file():
        return _from_file(Path(path), package=module.__package__ or None, display=module.__name__)
    return _call_build(module, module.__name__)


def _from_module_name(name: str) -> Model:
    if not all(part.isidentifier() for part in name.split(".")):
        raise ModelError(f"no model '{name}': not a paper model {list(PAPER_MODELS)}, a .py file or a module name")
    try:
        spec = importlib.util.find_spec(name)
    except (ImportError, ValueError) as exc:
        raise ModelError(f"no model '{name}': {exc}") from None
    if spec is None:
        raise ModelError(f"no model '{name}': not a paper model {list(PAPER_MODELS)}, "
                         "and no importable module of that name (a file path must end in .py)")
    if spec.origin and spec.origin.endswith(".py") and not spec.submodule_search_locations:
        return _from_file(Path(spec.origin), package=name.rpartition(".")[0] or None, display=name)
    return _call_build(importlib.import_module(name), name)


def _from_file(path: Path, package: str | None, display: str | None = None) -> Model:
    """Execute ``path`` as a fresh module (source read now; no bytecode cache) and call its build()."""
    display = display or str(path)
    try:
        source = path.read_bytes()
    except OSError as exc:
        raise ModelError(f"model file {path}: {exc.strerror or exc}") from None
    unique = f"_symkf_model_{next(_fresh_names)}_{path.stem if path.stem.isidentifier() else 'file'}"
    module = types.ModuleType(unique)
    module.__file__ = str(path.resolve())
    module.__package__ = package
    try:
        code = compile(source, str(path), "exec", dont_inherit=True)
    except SyntaxError as exc:
        raise ModelError(f"model file {path}, line {exc.lineno}: {exc.msg}; fix the file") from None
    folder = str(path.resolve().parent)
    added = package is None and folder not in sys.path
    if added:                              # a model file may import its siblings, as a script can
        sys.path.insert(0, folder)
    sys.modules[unique] = module           # dataclasses and pickling look their module up
    try:
        exec(code, module.__dict__)
    except (ModelError, KeyboardInterrupt):
        raise
    except Exception as exc:
        raise ModelError(_raised(exc, path, "executing it")) from exc
    finally:
        sys.modules.pop(unique, None)
        if added and folder in sys.path:
            sys.path.remove(folder)
    origin = "" if package == __name__ else display if package else str(path.resolve())
    return _call_build(module, display, source, origin)


def _call_build(module: types.ModuleType, display: str, source: bytes | None = None, origin: str | None = None) -> Model:
    build = getattr(module, "build", None)
    if not callable(build):
        raise ModelError(f"{display} defines no build() returning a Model")
    try:
        model = build()
    except ModelError:
        raise
    except Exception as exc:
        raise ModelError(_raised(exc, Path(getattr(module, "__file__", "") or display), "in build()")) from exc
    if model is None:
        raise ModelError(f"{display}: build() returned None; end it with `return model`")
    if not isinstance(model, Model):
        raise ModelError(f"{display}: build() returned a {type(model).__name__}, expected a symkf Model")
    if source is not None and not model.constants:
        model.constants = module_constants(module, source)
    if not model.source:
        model.source = display if origin is None else origin     # a module: its name; a file: its path
    return model.validate()


def _raised(exc: Exception, path: Path, when: str) -> str:
    """One line for an exception a model file raised: where in the file, what, and what to do."""
    line = next((frame.lineno for frame in reversed(traceback.extract_tb(exc.__traceback__))
                 if Path(frame.filename) == Path(path)), None)
    where = f", line {line}" if line else ""
    text = " ".join(str(exc).split()) or "(no message)"
    return f"model file {path}{where} raised {type(exc).__name__} {when}: {text}; fix the model file"


def module_constants(module: types.ModuleType, source: bytes) -> list[tuple[str, float | list[float], str]]:
    """Every module-level ``UPPER_CASE = number`` (or flat sequence of at most 64 finite numbers)
    of the executed ``source``, with its value as the build sees it and its line comment."""
    try:
        tree = ast.parse(source)
        comments = {tok.start[0]: tok.string.lstrip("# ") for tok in tokenize.tokenize(io.BytesIO(source).readline)
                    if tok.type == tokenize.COMMENT}
    except (SyntaxError, tokenize.TokenError):
        return []
    found = []
    for node in tree.body:
        if isinstance(node, ast.Assign) and len(node.targets) == 1 and isinstance(node.targets[0], ast.Name) \
                and re.fullmatch(r"[A-Z][A-Z0-9_]*", node.targets[0].id):
            value = _plain_number(getattr(module, node.targets[0].id, None))
            if value is not None:
                found.append((node.targets[0].id, value, comments.get(node.lineno, "")))
    return found


def _plain_number(value) -> float | list[float] | None:
    """A finite real number, or a flat list/tuple/1-D array of at most 64 of them; else None."""
    try:
        import numpy as np
        array = np.asarray(value)
    except Exception:
        return None
    if isinstance(value, bool) or array.dtype.kind not in "iuf" or array.ndim > 1 or array.size > 64 \
            or not all(math.isfinite(v) for v in array.ravel().tolist()):
        return None
    return float(array) if array.ndim == 0 else [float(v) for v in array]

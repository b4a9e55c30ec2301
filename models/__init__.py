"""Symbolic models (CasADi SX only). One file per system; ``get_model(name)`` builds one by name."""
from __future__ import annotations

import importlib

from .base import Measurement, Model, ModelError, Variable

__all__ = ["Measurement", "Model", "ModelError", "Variable", "get_model", "model_module"]


def model_module(name: str):
    """The module ``symkf.models.<name>``; a new model is a new file, nothing else changes."""
    if not name.isidentifier():
        raise ModelError(f"'{name}' is not a model name")
    try:
        return importlib.import_module(f"{__name__}.{name}")
    except ModuleNotFoundError as exc:
        if exc.name == f"{__name__}.{name}":
            raise ModelError(f"no model '{name}': expected a file models/{name}.py defining build()") from None
        raise


def get_model(name: str) -> Model:
    """Build and validate the model defined by ``models/<name>.py``'s ``build()``."""
    module = model_module(name)
    if not hasattr(module, "build"):
        raise ModelError(f"models/{name}.py defines no build() returning a Model")
    return module.build().validate()

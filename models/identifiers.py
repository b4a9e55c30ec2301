"""The naming rules for what becomes a C name: the model's name (it names the build folder and
every C function) and each measurement's (it names that measurement's kernels)."""
from __future__ import annotations

import re

from .errors import ModelError

C_IDENTIFIER = re.compile(r"[A-Za-z][A-Za-z0-9_]{0,47}")
C_KEYWORDS = frozenset("""auto break case char const continue default do double else enum extern float for goto if
    inline int long register restrict return short signed sizeof static struct switch typedef union unsigned void
    volatile while""".split())


def is_c_identifier(name) -> bool:
    """Letters, digits and '_', starting with a letter, at most 48 characters."""
    return isinstance(name, str) and C_IDENTIFIER.fullmatch(name) is not None


def check_model_name(name) -> None:
    """A model's name is a C identifier and not a C keyword."""
    if not is_c_identifier(name) or name in C_KEYWORDS:
        raise ModelError(f"model name {name!r} must be a C identifier (letters, digits, '_', not "
                         "starting with a digit or '_', at most 48 characters, not a C keyword): it names "
                         "the build folder and every C function")


def check_measurement_name(model: str, name) -> None:
    """A measurement's name is a C identifier."""
    if not is_c_identifier(name):
        raise ModelError(f"model '{model}': measurement name {name!r} must be a C identifier")

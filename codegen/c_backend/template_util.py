"""The C backend's static text: the C and Make fragments in ``templates/`` that do not depend on
the model (preprocessor blocks, the finiteness helper, the header's conventions, the Makefile),
read with importlib.resources so they ship in a regular install (pyproject.toml package-data)."""
from __future__ import annotations

import functools
import hashlib
from importlib import resources


@functools.lru_cache(maxsize=None)
def template_text(name: str) -> str:
    """The text of ``templates/<name>`` without its final newline (the file ends with one, as text
    files do; the callers join fragments with newlines). Fill-ins, if any, are str.format fields."""
    text = resources.files(__package__).joinpath("templates", name).read_text(encoding="ascii")
    return text[:-1] if text.endswith("\n") else text


@functools.lru_cache(maxsize=1)
def templates_digest() -> str:
    """SHA-256 over every template file (name and text): part of the content hash, so an edit of
    a template rebuilds like an edit of the code that fills it."""
    digest = hashlib.sha256()
    for path in sorted(resources.files(__package__).joinpath("templates").iterdir(), key=lambda p: p.name):
        digest.update(path.name.encode() + b"\0" + path.read_bytes() + b"\0")
    return digest.hexdigest()

"""Where builds go: a folder this user owns, never the current directory.

The build root is ``$SYMKF_BUILD_DIR``, else the source checkout's ``build/`` in a development
install, else a per-user cache (``$XDG_CACHE_HOME/symkf`` or ``~/.cache/symkf``), and it is
refused if other users can write to it. In it, a model's folder is named for the model and,
for any configuration but its default, a hash of that configuration.
"""
from __future__ import annotations

import hashlib
import json
import os
from dataclasses import asdict
from pathlib import Path

from symkf.models import Model
from .errors import BuildError
from .generation import default_config
from .spec import CodegenConfig

CODEGEN_DIR = Path(__file__).resolve().parent


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

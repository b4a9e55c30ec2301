"""Where builds go: a folder this user owns, never the current directory.

The build root is ``$SYMKF_BUILD_DIR``, else the source checkout's ``build/`` in a development
install, else a per-user cache (``$XDG_CACHE_HOME/symkf`` or ``~/.cache/symkf``), and it is
refused if another user owns it or can write to it. In it, a model's folder is named for the
model and, for any configuration but its default, a hash of that configuration.

One edit, one folder: a build is published as ``<folder>@<key16>`` (its content hash), a name no
other edit can race for, and ``<folder>`` is a symlink to the folder built last (what a person
or a Makefile opens as ``build/<model>``). The loader goes by the key, never by that symlink;
the :data:`KEEP` newest builds of a folder are kept (switching between edits rebuilds nothing).
"""
from __future__ import annotations

import hashlib
import json
import os
import re
import secrets
import shutil
from dataclasses import asdict
from pathlib import Path

from symkf.models import Model
from .errors import BuildError
from .generation import default_config
from .safe_files import ForeignFileError, check_owned
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
    if info.st_uid != os.geteuid():
        raise BuildError(f"build folder {root} is owned by uid {info.st_uid}, not by you (uid {os.geteuid()}): its owner "
                         "could replace a library in it; set SYMKF_BUILD_DIR to a folder you own")
    if info.st_mode & 0o022:
        raise BuildError(f"build folder {root} is writable by other users (mode {info.st_mode & 0o777:o}); "
                         f"a library there could be replaced: `chmod go-w {root}` or set SYMKF_BUILD_DIR")
    return root


def folder_name(model: Model, config: CodegenConfig) -> str:
    """``<name>`` for the model's default configuration, ``<name>-<cfg8>`` for any other."""
    if config == default_config(model):
        return model.name
    text = json.dumps(asdict(config), sort_keys=True, default=str)
    return f"{model.name}-{hashlib.sha256(text.encode()).hexdigest()[:8]}"


#: Builds kept per folder name (the newest, by the time they were published).
KEEP = 4


def keyed_name(folder: str, key: str) -> str:
    """The name a build of content hash ``key`` is published under: ``<folder>@<key16>``."""
    return f"{folder}@{key[:16]}"


def published(root: Path, folder: str) -> list[Path]:
    """The published builds of ``folder`` (``<folder>@<key16>``), newest first."""
    pattern = re.compile(re.escape(folder) + r"@[0-9a-f]{16}")
    found = []
    for path in root.glob(f"{glob_escape(folder)}@*"):
        try:
            if pattern.fullmatch(path.name):
                found.append((os.lstat(path).st_mtime_ns, path))
        except OSError:
            pass                                    # pruned meanwhile
    return [path for _, path in sorted(found, reverse=True)]


def glob_escape(text: str) -> str:
    return re.sub(r"([*?\[])", r"[\1]", text)


def current(root: Path, folder: str) -> Path | None:
    """The build ``<root>/<folder>`` points to, if it is this user's symlink to a published build."""
    link = root / folder
    try:
        info = os.lstat(link)
        target = os.readlink(link) if os.path.islink(link) else ""
    except OSError:
        return None
    if info.st_uid != os.geteuid() or not re.fullmatch(re.escape(folder) + r"@[0-9a-f]{16}", target):
        return None
    return root / target


def point_to(root: Path, folder: str, target: Path) -> None:
    """Make ``<root>/<folder>`` a symlink to the published build ``target`` (a new symlink renamed
    over the old one; a folder of this user's there, from an older symkf, is moved away first)."""
    link = root / folder
    if current(root, folder) == target:
        return
    try:
        info = os.lstat(link)
    except FileNotFoundError:
        info = None
    if info is not None and not os.path.islink(link):
        check_owned(link, info, "folder")                # never move away what another user made
        old = root / f".{folder}.old-{os.getpid()}-{secrets.token_hex(4)}"
        os.rename(link, old)
        shutil.rmtree(old, ignore_errors=True)
    elif info is not None and info.st_uid != os.geteuid():
        raise ForeignFileError(f"{link} is a symlink owned by uid {info.st_uid}, not by you; it was not used: "
                               "remove it (as its owner or root) or set SYMKF_BUILD_DIR to a folder only you own")
    temporary = root / f".{folder}.link-{secrets.token_hex(6)}"
    os.symlink(target.name, temporary)
    try:
        os.replace(temporary, link)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise


def prune(root: Path, folder: str, keep: int = KEEP) -> None:
    """Remove all but the ``keep`` newest published builds of ``folder`` (never the current one)."""
    pointed = current(root, folder)
    for path in published(root, folder)[keep:]:
        if path != pointed:
            old = root / f".{path.name}.old-{os.getpid()}-{secrets.token_hex(4)}"
            try:
                os.rename(path, old)                # a loader that has it open keeps its files
            except OSError:
                continue
            shutil.rmtree(old, ignore_errors=True)
            (root / f".{path.name}.lock").unlink(missing_ok=True)

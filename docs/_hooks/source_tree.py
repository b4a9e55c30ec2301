"""MkDocs hook: the ``symkf`` package as one folder for the API reference.

symkf is installed from five folders (``package/`` is ``symkf`` itself, ``models/`` is
``symkf.models``, ...: the package-dir mapping of pyproject.toml), which mkdocstrings' static
reader cannot follow. Before the build, this hook lays ``build/docs-src/symkf/`` out as symbolic
links to those folders; ``mkdocs.yml`` points the Python handler there.
"""
from __future__ import annotations

from pathlib import Path

from mkdocs.plugins import event_priority

ROOT = Path(__file__).resolve().parents[2]
#: Sub-package -> folder, as pyproject.toml maps them.
FOLDERS = {"models": "models", "codegen": "codegen", "runtime": "runtime", "scenarios": "scenarios"}


@event_priority(100)                 # before mkdocstrings reads its handler's paths
def on_config(config, **kwargs):
    tree = ROOT / "build" / "docs-src" / "symkf"
    tree.mkdir(parents=True, exist_ok=True)
    links = {"__init__.py": ROOT / "package" / "__init__.py",
             **{name: ROOT / folder for name, folder in FOLDERS.items()}}
    for name, target in links.items():
        link = tree / name
        if link.is_symlink() and link.resolve() == target.resolve():
            continue
        if link.is_symlink() or link.exists():
            link.unlink()
        link.symlink_to(target)
    return config

"""The one reader of a build folder's ``manifest.json``, used by the build and by the runtime.

The manifest records the content hash of what was built, the generated hash, and the name and
SHA-256 of the per-build copy of the library Python loads: a folder is up to date and its library
may be opened only if that SHA-256 matches the file (a damaged or replaced library is rebuilt,
never opened). :func:`verified_manifest` reads the manifest once and hashes the library once.
"""
from __future__ import annotations

import hashlib
import json
from pathlib import Path


def sha256_file(path: Path) -> str:
    """SHA-256 of a file, read in blocks."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def read_manifest(directory: Path) -> dict | None:
    """The folder's manifest.json, or None if it is missing, unreadable or lacks the library's record."""
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


def verified_manifest(directory: Path, key: str | None = None, field: str = "content_hash") -> dict | None:
    """The folder's manifest if its library matches the recorded SHA-256 (and, given ``key``, its
    ``field`` is ``key``: the folder is up to date), else None. Reads the manifest once and hashes
    the library once: a load checks with this and opens the library with what it returns."""
    manifest = read_manifest(directory)
    if manifest is None or (key is not None and manifest.get(field) != key):
        return None
    return manifest if verified_library(directory, manifest) is not None else None


"""The one reader of a build folder's ``manifest.json``, used by the build and by the runtime.

The manifest records the content hash of what was built, the generated hash, the name and
SHA-256 of the per-build copy of the library Python loads, and under "files" the SHA-256 of
every other file of the flight bundle (the C units, the header, the Makefile, ``lib<name>.so``).
A folder is up to date, and its library may be opened, only if every one of them matches: a
missing, damaged or edited file makes the folder stale and the build regenerates it, saying why
(:func:`folder_state`). The folder and its files are read only if this user made them
(:mod:`symkf.codegen.safe_files`); :func:`verified_manifest` reads the manifest once and hashes
each file once.
"""
from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

from .safe_files import check_folder, read_checked, sha256_checked


def sha256_file(path: Path) -> str:
    """SHA-256 of a file of this user's, read without following a symlink."""
    return sha256_checked(path)


def sha256_bytes(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def read_manifest(directory: Path) -> dict | None:
    """The folder's manifest.json, or None if it is missing, unreadable or lacks the library's record.
    A folder or manifest another user made is refused (:class:`~symkf.codegen.safe_files.ForeignFileError`)."""
    try:
        check_folder(directory)
        manifest = json.loads(read_checked(directory / "manifest.json"))
        manifest["content_hash"], manifest["library_sha256"], manifest["hashed_library"]
        return manifest
    except (OSError, ValueError, KeyError, TypeError):       # missing, half written, unreadable: rebuilt
        return None


def _plain_name(name) -> bool:
    return isinstance(name, str) and name not in ("", ".", "..") and Path(name).name == name


def damaged_file(directory: Path, manifest: dict) -> str:
    """Why the folder's files do not match the manifest ("" if every one does): the first file
    missing or whose SHA-256 differs from the recorded one, the hashed library included."""
    name = manifest["hashed_library"]
    if not _plain_name(name) or not name.endswith(".so"):
        return "the manifest names no library"
    files = manifest.get("files")
    if not isinstance(files, dict) or not all(_plain_name(f) for f in files):
        return "the manifest records no digest of the bundle's files (made by an older symkf)"
    for file, digest in [(name, manifest["library_sha256"])] + sorted(files.items()):
        try:
            if sha256_file(directory / file) != digest:
                return f"{file} does not match its digest in the manifest (modified or damaged)"
        except FileNotFoundError:
            return f"{file} is missing"
    return ""


def folder_state(directory: Path, key: str | None = None, field: str = "content_hash") -> tuple[dict | None, str]:
    """(manifest, "") if the folder is complete and every file matches its digest (and, given
    ``key``, its ``field`` is ``key``: the folder is up to date); else (None, why not)."""
    manifest = read_manifest(directory)
    if manifest is None:
        return None, ("not built" if not os.path.lexists(directory / "manifest.json")
                      else "manifest.json is unreadable or incomplete")
    if key is not None and manifest.get(field) != key:
        return None, "built from other sources"
    why = damaged_file(directory, manifest)
    return (None, why) if why else (manifest, "")


def verified_manifest(directory: Path, key: str | None = None, field: str = "content_hash") -> dict | None:
    """The folder's manifest if its library and every bundle file match their digests (and, given
    ``key``, its ``field`` is ``key``), else None (:func:`folder_state` says why)."""
    return folder_state(directory, key, field)[0]

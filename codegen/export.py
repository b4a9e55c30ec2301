"""``symkf build X --out DIR``: the flight bundle exported whole or not at all, never through a symlink.

:func:`export_bundle` copies the files the manifest records (the C units, the header, the
Makefile, ``lib<name>.so``) and the manifest itself, each only if its bytes match the SHA-256 the
manifest records (the build verified them, so a mismatch means a file changed since: the export
is refused). The copies go to a staging folder (created exclusively, private) which is renamed to
``DIR`` when ``DIR`` does not exist: the export is whole or absent. Into an existing ``DIR`` (a
shared folder), a file already there that is a symlink, not a regular file or not this user's is
refused before anything is written; then each staged file is renamed over its name (a rename
replaces a name, it never writes through a symlink), the manifest last.
"""
from __future__ import annotations

import json
import os
import shutil
import stat
import tempfile
from pathlib import Path

from .errors import BuildError
from .manifest import sha256_bytes
from .safe_files import read_checked


def export_bundle(result, out: Path) -> list[Path]:
    """Copy the verified flight bundle of ``result`` (a :class:`~symkf.codegen.lifecycle.BuildResult`)
    into ``out``; returns the paths written. Raises BuildError (one line) and writes nothing
    when ``out`` or a file in it is not this user's to replace, or a bundle file does not match
    its digest."""
    out = Path(out)
    manifest = result.record or json.loads(read_checked(result.manifest))
    files = manifest.get("files")
    if not isinstance(files, dict) or not files:
        raise BuildError(f"{result.manifest} records no digests of the bundle's files; rebuild with "
                         f"`symkf build {result.model} --force`")
    names = sorted(files) + ["manifest.json"]
    existing = _check_destination(out, names)
    parent = out if existing else out.parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
        staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.export-", dir=parent))
    except OSError as exc:
        raise BuildError(f"--out {out}: cannot create a folder there ({exc.strerror or exc}): choose a folder you "
                         "can write") from None
    try:
        for name in names:
            data = read_checked(result.directory / name)
            if (sha256_bytes(data) != files[name]) if name != "manifest.json" else not _same_build(data, manifest):
                raise BuildError(f"{result.directory / name} changed after it was verified; nothing was exported: "
                                 f"run `symkf build {result.model} --out {out}` again")
            _write_new(staging / name, data, 0o755 if name.endswith(".so") else 0o644)
        if not existing:
            os.chmod(staging, 0o755)
            os.rename(staging, out)                         # whole or absent
        else:
            for name in names:                              # the manifest last
                os.rename(staging / name, out / name)
            staging.rmdir()
    except OSError as exc:
        shutil.rmtree(staging, ignore_errors=True)
        where = f" ({exc.filename})" if exc.filename else ""
        raise BuildError(f"exporting to {out}: {exc.strerror or exc}{where}; the staged copies were removed") from None
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return [out / name for name in names]


def _same_build(data: bytes, manifest: dict) -> bool:
    """Whether manifest.json's bytes are the manifest of the build being exported."""
    try:
        read = json.loads(data)
    except ValueError:
        return False
    return isinstance(read, dict) and all(read.get(k) == manifest.get(k)
                                          for k in ("content_hash", "library_sha256", "files"))


def _check_destination(out: Path, names: list[str]) -> bool:
    """Whether ``out`` exists (as a folder of its own, not a symlink); refuses a file in it that
    the export would replace and that is a symlink, not a regular file or not this user's."""
    try:
        info = os.lstat(out)
    except FileNotFoundError:
        return False
    if stat.S_ISLNK(info.st_mode):
        raise BuildError(f"--out {out} is a symlink; nothing was exported: give the folder it points to, if it is "
                         "yours")
    if not stat.S_ISDIR(info.st_mode):
        raise BuildError(f"--out {out} exists and is not a folder; nothing was exported")
    for name in names:
        try:
            target = os.lstat(out / name)
        except FileNotFoundError:
            continue
        if stat.S_ISLNK(target.st_mode) or not stat.S_ISREG(target.st_mode) or target.st_uid != os.geteuid():
            what = ("a symlink" if stat.S_ISLNK(target.st_mode) else "not a regular file"
                    if not stat.S_ISREG(target.st_mode) else f"owned by uid {target.st_uid}, not by you")
            raise BuildError(f"--out {out}: {out / name} is {what}; nothing was exported: remove it (or export to a "
                             "folder of your own)")
    return True


def _write_new(path: Path, data: bytes, mode: int) -> None:
    """Create ``path`` exclusively (never through a symlink) with ``data``."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC, mode)
    try:
        view = memoryview(data)
        while view:
            view = view[os.write(fd, view):]
    finally:
        os.close(fd)
    os.chmod(path, mode)                                    # whatever the umask

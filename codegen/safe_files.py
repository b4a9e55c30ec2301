"""Files in the build root used only if this user made them; writes that never follow a symlink.

Another user who can place a folder, an object or a library where the build or the loader looks
gets code run in this user's process, and a symlink planted where a file is written turns the
write against a file of this user's. So, inside the build root:

- every folder is checked with ``lstat`` before anything in it is used (:func:`check_folder`): a
  real folder, not a symlink, owned by this user, not writable by group or others;
- every file is opened with ``O_NOFOLLOW`` and checked on its descriptor (:func:`open_checked`):
  a regular file of this user's, not writable by others, hashed from that descriptor; a library
  loaded afterwards by name is checked to be that same file (:func:`mapped_is`);
- every write goes to a temporary created with ``O_CREAT | O_EXCL | O_NOFOLLOW`` in a checked
  folder, renamed into place once complete (:func:`write_exclusive`).

A refusal names the file and the fix; for a file another user owns the fix is ownership (remove
it, or build somewhere else), never ``chmod``.
"""
from __future__ import annotations

import errno
import hashlib
import os
import secrets
import stat
from pathlib import Path

from .errors import BuildError


class ForeignFileError(BuildError):
    """A folder or file in the build root that this user did not make (or may be replaced by others)."""


def check_owned(path: Path, info: os.stat_result, kind: str) -> None:
    """Refuse ``path`` unless it is a ``kind`` ("folder" or "file") this user owns that no other user can write."""
    uid = os.geteuid()
    if stat.S_ISLNK(info.st_mode):
        raise ForeignFileError(f"{path} is a symlink where symkf expects a {kind} of its own; it was not followed: "
                               "remove it (or set SYMKF_BUILD_DIR to a folder only you own)")
    if not (stat.S_ISDIR(info.st_mode) if kind == "folder" else stat.S_ISREG(info.st_mode)):
        raise ForeignFileError(f"{path} is not a regular {kind}; it was not used: remove it")
    if info.st_uid != uid:
        raise ForeignFileError(f"{path} is owned by uid {info.st_uid}, not by you (uid {uid}); it was not used: "
                               "another user may have planted it. Remove it (as its owner or root) or set "
                               "SYMKF_BUILD_DIR to a folder only you own")
    if info.st_mode & 0o022:
        raise ForeignFileError(f"{path} is writable by other users (mode {info.st_mode & 0o777:o}); it was not used: "
                               f"remove it (symkf makes it again) or `chmod go-w {path}`")


def check_folder(path: Path, create: bool = False) -> Path:
    """``path`` if it is a folder of this user's (see :func:`check_owned`); ``create``: made (mode 755) if absent."""
    try:
        info = os.lstat(path)
    except FileNotFoundError:
        if not create:
            raise
        try:
            os.mkdir(path, 0o755)
        except FileExistsError:
            pass                                       # made meanwhile by another build: checked below
        info = os.lstat(path)
    check_owned(path, info, "folder")
    return path


def open_checked(path: Path) -> int:
    """A read-only descriptor of ``path``, not followed if a symlink, refused unless a file of this user's."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC | getattr(os, "O_NONBLOCK", 0))
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            check_owned(path, os.lstat(path), "file")
        raise
    try:
        check_owned(path, os.fstat(fd), "file")
    except BaseException:
        os.close(fd)
        raise
    return fd


def sha256_fd(fd: int) -> str:
    """SHA-256 of what an open descriptor reads from its start."""
    digest = hashlib.sha256()
    os.lseek(fd, 0, os.SEEK_SET)
    while block := os.read(fd, 1 << 20):
        digest.update(block)
    return digest.hexdigest()


def read_checked(path: Path) -> bytes:
    """The bytes of ``path`` (:func:`open_checked`)."""
    fd = open_checked(path)
    try:
        chunks = []
        while block := os.read(fd, 1 << 20):
            chunks.append(block)
        return b"".join(chunks)
    finally:
        os.close(fd)


def sha256_checked(path: Path) -> str:
    """SHA-256 of ``path`` (:func:`open_checked`)."""
    fd = open_checked(path)
    try:
        return sha256_fd(fd)
    finally:
        os.close(fd)


def mapped_is(fd: int, path: Path) -> bool:
    """Whether every mapping of ``path`` in this process (``/proc/self/maps``) is of the file
    open as ``fd`` (same device and inode): a library loaded by name is the one that was hashed.
    True where the system has no such table. (A library is loaded by its name, not as
    ``/proc/self/fd/N``: the dynamic loader matches names, and a reused descriptor number would
    give back another library loaded under the same name.)"""
    info = os.fstat(fd)
    target = os.path.realpath(path)
    try:
        with open("/proc/self/maps") as maps:
            rows = [line.split(maxsplit=5) for line in maps]
    except OSError:
        return True
    found = [row for row in rows if len(row) == 6 and row[5].rstrip("\n") == target]
    device = f"{os.major(info.st_dev):02x}:{os.minor(info.st_dev):02x}"
    return bool(found) and all(int(row[4]) == info.st_ino and row[3] == device for row in found)


def write_exclusive(path: Path, data: bytes | str, mode: int = 0o644) -> None:
    """Write ``data`` to ``path``: a temporary created exclusively (never a followed symlink) next
    to it, renamed over ``path`` once complete; on any failure the temporary is removed."""
    temporary = path.parent / f".{path.name}.{secrets.token_hex(6)}.tmp"
    payload = data.encode() if isinstance(data, str) else data
    fd = os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC, mode)
    try:
        try:
            view = memoryview(payload)
            while view:
                view = view[os.write(fd, view):]
        finally:
            os.close(fd)
        os.replace(temporary, path)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise


def copy_checked(source: Path, target: Path, mode: int = 0o644) -> str:
    """Copy a file of this user's (:func:`open_checked`) to ``target`` (:func:`write_exclusive`);
    returns the SHA-256 of the bytes copied."""
    data = read_checked(source)
    write_exclusive(target, data, mode)
    return hashlib.sha256(data).hexdigest()

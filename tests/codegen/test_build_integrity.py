"""Trust nothing in the build root this user did not make: a model folder, an object cache entry,
a fast-path extension or a lock planted by another user is refused, naming it and the fix, and
its code never runs; writes never follow a symlink.

Another user is simulated by root giving the planted files to uid 12345 (skipped when not root).
A planted library's constructor writes a marker file: the marker must never appear.
"""
import os
import subprocess
import sysconfig
import warnings

import pytest

from symkf.codegen import BuildError, build_model, compiler, make_config
from symkf.codegen import hashing
from symkf.codegen.build_folders import keyed_name
from symkf.codegen.safe_files import ForeignFileError, open_checked, write_exclusive
from symkf.models import get_model
from symkf.runtime import fastcall, load

FOREIGN = 12345
needs_root = pytest.mark.skipif(os.geteuid() != 0, reason="needs root to give files to another uid")

PLANTED = r"""
#include <stdio.h>
__attribute__((constructor)) static void planted(void) {
  FILE *f = fopen("%(marker)s", "w");
  if (f) { fputs("foreign code ran\n", f); fclose(f); }
}
const char *tiny_content_hash(void) { return "%(key)s"; }
int PyInit__symkf_fastcall(void) { return 0; }
"""


@pytest.fixture
def root(tmp_path, monkeypatch):
    root = tmp_path / "build"
    monkeypatch.setenv("SYMKF_BUILD_DIR", str(root))
    return root


def _planted_library(path, marker, key="") -> None:
    """A shared library at ``path`` whose constructor writes ``marker``."""
    source = path.with_suffix(".c")
    source.write_text(PLANTED % {"marker": marker, "key": key})
    subprocess.run(compiler().split() + ["-shared", "-fPIC", "-o", str(path), str(source)], check=True)
    source.unlink()


def _give_away(path) -> None:
    """Every file and folder under ``path`` (and itself) to uid FOREIGN, as another user's."""
    for folder, dirs, files in os.walk(path):
        for name in dirs + files:
            os.lchown(os.path.join(folder, name), FOREIGN, FOREIGN)
    os.lchown(path, FOREIGN, FOREIGN)


def _key(path) -> str:
    model = get_model(str(path))
    return hashing.content_hash(model, make_config(model), compiler())


@needs_root
def test_a_model_folder_of_another_user_is_refused_and_its_library_never_runs(tmp_path, write_model, root):
    path = write_model(tmp_path / "tracker.py")
    key, marker = _key(path), tmp_path / "marker"
    folder = root / keyed_name("tiny", key)
    folder.mkdir(parents=True)
    os.chmod(root, 0o755)
    _planted_library(folder / "libtiny.x.so", marker, key)
    (folder / "manifest.json").write_text('{"model": "tiny", "content_hash": "%s", "library_sha256": "x", '
                                          '"hashed_library": "libtiny.x.so", "files": {}}' % key)
    _give_away(folder)
    with pytest.raises(ForeignFileError) as info:
        load(str(path))
    text = str(info.value)
    assert str(folder) in text and f"owned by uid {FOREIGN}" in text and "chmod" not in text and "\n" not in text
    assert not marker.exists()


@needs_root
def test_a_foreign_folder_under_the_models_plain_name_is_never_used(tmp_path, write_model, root):
    """``<root>/tiny`` (the pointer people open) planted as another user's folder: the loader goes
    by the content hash and never opens it; the pointer is left alone."""
    path = write_model(tmp_path / "tracker.py")
    marker = tmp_path / "marker"
    planted = root / "tiny"
    planted.mkdir(parents=True)
    _planted_library(planted / "libtiny.so", marker)
    _give_away(planted)
    compiled = load(str(path))
    assert compiled.build.directory.name.startswith("tiny@") and not marker.exists()
    assert planted.is_dir() and not planted.is_symlink() and os.lstat(planted).st_uid == FOREIGN


@needs_root
def test_a_planted_object_cache_entry_is_refused_never_linked(tmp_path, write_model, root):
    """The cache key is computable from public sources: an attacker's object with a matching sum."""
    path = write_model(tmp_path / "tracker.py")
    build_model(str(path))
    marker = tmp_path / "marker"
    evil = tmp_path / "evil.o"
    (tmp_path / "evil.c").write_text(PLANTED % {"marker": marker, "key": ""})
    subprocess.run(compiler().split() + ["-c", "-fPIC", "-o", str(evil), str(tmp_path / "evil.c")], check=True)
    import hashlib
    import json
    digest = hashlib.sha256(evil.read_bytes()).hexdigest()
    for entry in (root / ".objects").glob("*.sum"):
        sums = json.loads(entry.read_text())
        entry.with_suffix(".o").write_bytes(evil.read_bytes())
        entry.write_text(json.dumps(dict(sums, **{".o": digest})))
        for suffix in sums:
            os.chown(entry.with_suffix(suffix), FOREIGN, FOREIGN)
        os.chown(entry, FOREIGN, FOREIGN)
    with pytest.raises(ForeignFileError, match=f"owned by uid {FOREIGN}") as info:
        build_model(str(path), force=True)
    assert ".objects" in str(info.value) and not marker.exists()


@needs_root
def test_an_object_cache_folder_of_another_user_is_refused(tmp_path, write_model, root):
    (root / ".objects").mkdir(parents=True)
    os.chown(root / ".objects", FOREIGN, FOREIGN)
    with pytest.raises(ForeignFileError, match=r"\.objects is owned by uid 12345"):
        build_model(str(write_model(tmp_path / "tracker.py")))


@pytest.fixture
def fresh_extension():
    """fastcall.extension() found afresh in this test, and again afterwards (its cache cleared)."""
    fastcall.extension.cache_clear()
    yield
    fastcall.extension.cache_clear()


def _extension_folder(root):
    key = fastcall._key(compiler(), sysconfig.get_paths()["include"])
    return root / "_fastcall" / key[:16], fastcall.MODULE + (sysconfig.get_config_var("EXT_SUFFIX") or ".so")


@needs_root
def test_a_planted_fast_path_extension_is_refused_and_never_imported(tmp_path, root, fresh_extension):
    folder, name = _extension_folder(root)
    folder.mkdir(parents=True)
    os.chmod(root, 0o755)
    marker = tmp_path / "marker"
    _planted_library(folder / name, marker)
    import hashlib
    (folder / "sha256").write_text(hashlib.sha256((folder / name).read_bytes()).hexdigest())
    _give_away(folder)
    with pytest.warns(RuntimeWarning, match=f"fast path is off: .*owned by uid {FOREIGN}"):
        assert fastcall.extension() is None
    assert str(folder) in fastcall.unavailable and not marker.exists()


def test_a_symlinked_digest_record_is_replaced_never_written_through(tmp_path, root, fresh_extension):
    """The extension is missing, so it is compiled and its record written: the planted symlink
    named like the record is replaced (a new file renamed over it), the victim is untouched."""
    folder, _ = _extension_folder(root)
    folder.mkdir(parents=True)
    victim = tmp_path / "victim"
    victim.write_text("29 bytes of the victim's file")
    (folder / "sha256").symlink_to(victim)
    assert fastcall.extension() is not None
    assert victim.read_text() == "29 bytes of the victim's file"
    assert not (folder / "sha256").is_symlink() and len((folder / "sha256").read_text()) == 64


def test_a_symlinked_digest_record_beside_an_extension_is_refused(tmp_path, root, fresh_extension):
    folder, _ = _extension_folder(root)
    assert fastcall.extension() is not None                  # built, with its record
    fastcall.extension.cache_clear()
    victim = tmp_path / "victim"
    victim.write_text((folder / "sha256").read_text())
    (folder / "sha256").unlink()
    (folder / "sha256").symlink_to(victim)
    with pytest.warns(RuntimeWarning, match="sha256 is a symlink"):
        assert fastcall.extension() is None
    assert (folder / "sha256").is_symlink()


@needs_root
def test_a_lock_file_of_another_user_is_refused(tmp_path, write_model, root):
    path = write_model(tmp_path / "tracker.py")
    root.mkdir()
    lock = root / f".{keyed_name('tiny', _key(path))}.lock"
    lock.write_text("")
    os.chown(lock, FOREIGN, FOREIGN)
    with pytest.raises(ForeignFileError, match=f"owned by uid {FOREIGN}"):
        build_model(str(path))


@needs_root
def test_a_build_root_of_another_user_is_refused_for_its_owner_not_its_mode(tmp_path, write_model, root):
    root.mkdir(mode=0o755)
    os.chown(root, FOREIGN, FOREIGN)
    with pytest.raises(BuildError) as info:
        build_model(str(write_model(tmp_path / "tracker.py")))
    assert f"owned by uid {FOREIGN}" in str(info.value) and "chmod" not in str(info.value)


def test_a_library_replaced_by_a_symlink_is_refused(tmp_path, write_model, root):
    path = write_model(tmp_path / "tracker.py")
    result = build_model(str(path))
    other = tmp_path / "elsewhere.so"
    other.write_bytes(result.library.read_bytes())
    result.library.unlink()
    result.library.symlink_to(other)
    with pytest.raises(ForeignFileError, match=f"{result.library.name} is a symlink .* not followed: remove it"):
        load(str(path))
    with pytest.raises(ForeignFileError, match="is a symlink"):
        open_checked(result.library)


def test_writes_replace_a_planted_symlink_never_follow_it(tmp_path):
    victim, target = tmp_path / "victim", tmp_path / "record"
    victim.write_text("victim")
    target.symlink_to(victim)
    write_exclusive(target, "new text")
    assert victim.read_text() == "victim" and not target.is_symlink() and target.read_text() == "new text"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["record", "victim"]       # no temporary left


def test_a_fresh_process_with_the_fast_path_still_works(tmp_path, write_model, root):
    """The checks do not cost the fast path: it builds, verifies and imports from a fresh root."""
    code = ("from symkf.runtime import fastcall; m = fastcall.extension(); "
            "print('ok' if m is not None else fastcall.unavailable)")
    env = dict(os.environ, SYMKF_BUILD_DIR=str(root))
    with warnings.catch_warnings():
        out = subprocess.run([os.sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert out.stdout.strip() == "ok", out.stderr[-2000:]

"""The flight bundle is verified like the library: the manifest records every file's digest, a
missing or edited file is regenerated (saying so), and ``symkf build X --out DIR`` exports only
verified files, whole or not at all, never through a symlink or over another user's file."""
import errno
import hashlib
import json
import os

import pytest

from symkf.codegen import BuildError, BundleRepairWarning, build_model, export
from symkf.runtime import load
from symkf.scenarios.cli import main

FOREIGN_UID = 12345


@pytest.fixture(scope="module")
def shared_root(tmp_path_factory):
    return tmp_path_factory.mktemp("bundle_root")


@pytest.fixture
def tiny(tmp_path, write_model, shared_root, monkeypatch):
    """A built user model (one build root for the module: the object cache is shared)."""
    monkeypatch.setenv("SYMKF_BUILD_DIR", str(shared_root))
    path = write_model(tmp_path / "tracker.py")
    return path, build_model(str(path))


def _sha(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_manifest_records_every_bundle_file(tiny):
    _, result = tiny
    files = result.record["files"]
    assert set(files) == set(result.record["sources"]) | {"tiny.h", "Makefile", "libtiny.so"}
    for name, digest in files.items():
        assert _sha(result.directory / name) == digest, name


@pytest.mark.parametrize("damage, why", [
    (lambda d: (d / "tiny.h").unlink(), "tiny.h is missing"),
    (lambda d: (d / "tiny_api.c").write_text((d / "tiny_api.c").read_text() + "int garbage = ;\n"),
     "tiny_api.c does not match its digest"),
    (lambda d: (d / "Makefile").unlink(), "Makefile is missing"),
    (lambda d: (d / "libtiny.so").write_bytes(bytes((d / "libtiny.so").stat().st_size)),      # zeroed
     "libtiny.so does not match its digest")])
def test_a_missing_or_modified_file_is_regenerated_saying_so(tiny, capsys, damage, why):
    path, result = tiny
    damage(result.directory)
    assert main(["build", str(path)]) == 0
    out = capsys.readouterr().out
    assert f"tiny: {why}" in out and "regenerated the bundle" in out and "up to date" not in out
    for name, digest in json.loads(result.manifest.read_text())["files"].items():
        assert _sha(result.directory / name) == digest, name
    assert "garbage" not in (result.directory / "tiny_api.c").read_text()


def test_load_regenerates_a_damaged_bundle_with_a_warning(tiny):
    path, result = tiny
    (result.directory / "tiny_k_f.c").write_text("/* edited */\n")
    with pytest.warns(BundleRepairWarning, match="tiny_k_f.c does not match its digest"):
        compiled = load(str(path))
    assert not compiled.build.up_to_date and compiled.build.repaired
    assert _sha(result.directory / "tiny_k_f.c") == compiled.build.record["files"]["tiny_k_f.c"]


def test_export_of_a_damaged_build_rebuilds_first_and_exports_verified_files(tiny, tmp_path, capsys):
    path, result = tiny
    (result.directory / "libtiny.so").write_bytes(bytes(4096))
    (result.directory / "tiny.h").unlink()
    out = tmp_path / "flight"
    assert main(["build", str(path), "--out", str(out)]) == 0
    assert "regenerated the bundle" in capsys.readouterr().out
    manifest = json.loads((out / "manifest.json").read_text())
    assert sorted(p.name for p in out.iterdir()) == sorted(list(manifest["files"]) + ["manifest.json"])
    for name, digest in manifest["files"].items():
        assert _sha(out / name) == digest, name
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".flight")]      # no staging left


def test_symlinks_planted_in_out_are_refused_and_nothing_is_written(tiny, tmp_path, capsys):
    path, result = tiny
    out, victim = tmp_path / "shared", tmp_path / "victim.txt"
    out.mkdir()
    victim.write_text("the victim's file\n")
    (out / "tiny.h").symlink_to(victim)
    assert main(["build", str(path), "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "is a symlink" in err and "Traceback" not in err
    assert victim.read_text() == "the victim's file\n"
    assert sorted(p.name for p in out.iterdir()) == ["tiny.h"] and (out / "tiny.h").is_symlink()


def test_out_itself_a_symlink_is_refused(tiny, tmp_path, capsys):
    path, _ = tiny
    (tmp_path / "real").mkdir()
    (tmp_path / "link").symlink_to(tmp_path / "real")
    assert main(["build", str(path), "--out", str(tmp_path / "link")]) == 1
    assert "is a symlink" in capsys.readouterr().err and not any((tmp_path / "real").iterdir())


@pytest.mark.skipif(os.geteuid() != 0, reason="needs root to give a file to another uid")
def test_a_file_of_another_user_in_out_is_refused(tiny, tmp_path, capsys):
    path, _ = tiny
    out = tmp_path / "shared"
    out.mkdir()
    (out / "Makefile").write_text("theirs\n")
    os.chown(out / "Makefile", FOREIGN_UID, FOREIGN_UID)
    assert main(["build", str(path), "--out", str(out)]) == 1
    assert f"owned by uid {FOREIGN_UID}" in capsys.readouterr().err
    assert (out / "Makefile").read_text() == "theirs\n" and sorted(p.name for p in out.iterdir()) == ["Makefile"]


def test_export_into_an_existing_folder_replaces_own_files_and_keeps_others(tiny, tmp_path):
    _, result = tiny
    out = tmp_path / "shared"
    out.mkdir()
    (out / "notes.txt").write_text("mine\n")
    (out / "tiny.h").write_text("an old header\n")
    export.export_bundle(result, out)
    assert (out / "notes.txt").read_text() == "mine\n"
    assert _sha(out / "tiny.h") == result.record["files"]["tiny.h"]


def test_a_failed_export_leaves_nothing(tiny, tmp_path, monkeypatch, capsys):
    """A disk that fills during the export: one line, and no half bundle, no staging folder."""
    path, _ = tiny
    written = []
    original = export._write_new

    def filling(target, data, mode):
        if len(written) == 3:
            raise OSError(errno.ENOSPC, "No space left on device", str(target))
        written.append(target)
        original(target, data, mode)
    monkeypatch.setattr(export, "_write_new", filling)
    out = tmp_path / "flight"
    assert main(["build", str(path), "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "No space left on device" in err and "Traceback" not in err
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["tracker.py"]


def test_a_file_changed_after_the_check_is_not_exported(tiny, tmp_path):
    _, result = tiny
    (result.directory / "tiny_k_fd.c").write_text("int garbage = ;\n")
    with pytest.raises(BuildError, match="tiny_k_fd.c changed after it was verified"):
        export.export_bundle(result, tmp_path / "flight")
    assert not (tmp_path / "flight").exists()

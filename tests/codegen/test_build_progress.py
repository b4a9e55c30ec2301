"""A cold build says on stderr, from its first second, which model it builds and how many C units
are compiled of how many; a cached build says nothing (codegen/progress.py)."""
import io
import re

from symkf.codegen import build_model
from symkf.codegen.progress import BuildProgress


def test_a_cold_build_shows_units_done_of_total_and_a_cached_one_is_quiet(tmp_path, write_model, monkeypatch, capsys):
    monkeypatch.setenv("SYMKF_BUILD_DIR", str(tmp_path / "build"))
    path = write_model(tmp_path / "tracker.py")
    capsys.readouterr()
    result = build_model(str(path))
    lines = capsys.readouterr().err.splitlines()
    assert lines[0].startswith("symkf: building tiny (generating C")
    counts = [tuple(map(int, m.groups())) for m in (re.search(r": (\d+)/(\d+) C units compiled", x) for x in lines) if m]
    assert counts and all(done <= total for done, total in counts)
    assert counts[-1] == (len(result.compiled), len(result.compiled))        # the last count: all of them
    assert re.fullmatch(rf"symkf: built tiny in [\d.]+ s: {len(result.compiled)} C units compiled.*", lines[-1])
    assert not build_model(str(path)).compiled and capsys.readouterr().err == ""     # cached: silent


def test_a_log_gets_a_line_per_interval_a_terminal_one_line_rewritten():
    log = io.StringIO()
    progress = BuildProgress("demo", stream=log)
    progress.begin()
    for done in range(1, 6):
        progress.units(done, 5, final=True)
    progress.end(5, 7)
    lines = log.getvalue().splitlines()
    assert lines[0].startswith("symkf: building demo") and "1/5 C units compiled" in lines[1]
    assert "5/5 C units compiled" in lines[-2] and len(lines) == 4            # first, last count; not each unit
    assert lines[-1].endswith("5 C units compiled, 2 from the object cache")

    class Terminal(io.StringIO):
        def isatty(self):
            return True
    screen = Terminal()
    progress = BuildProgress("demo", stream=screen)
    progress.units(1, 3)
    progress.units(2, 3)
    assert screen.getvalue().count("\r") == 2 and "\n" not in screen.getvalue()
    assert "2/3 C units compiled (still generating)" in screen.getvalue()

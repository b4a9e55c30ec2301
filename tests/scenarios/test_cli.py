"""`symkf compare` and `symkf bench` find their experiments and benches in the installed package:
`--help` lists each with a one-line description, an unknown name lists the valid ones, and every
listed name answers its own `--help`."""
import re

import pytest

from symkf.scenarios.cli import entries, main

BENCHES = {"attitude", "build", "float", "geo", "launcher", "marg"}
EXPERIMENTS = {"attitude", "geo", "launcher", "marg"}


@pytest.mark.parametrize("kind, names", [("bench", BENCHES), ("compare", EXPERIMENTS)])
def test_help_lists_every_name_with_a_description(capsys, kind, names):
    assert set(entries(kind)) == names
    assert main([kind, "--help"]) == 0
    listed = dict(re.findall(r"^  (\w+) +(\S.*)$", capsys.readouterr().out, flags=re.M))
    assert set(listed) == names
    for name, text in listed.items():
        assert len(text) > 20 and not re.search(r"issue \d|scenarios/", text), (name, text)


@pytest.mark.parametrize("kind", ["bench", "compare"])
def test_an_unknown_name_lists_the_valid_ones(capsys, kind):
    assert main([kind, "foo"]) == 2
    err = capsys.readouterr().err
    assert "'foo'" in err and "scenarios/" not in err
    assert all(name in err for name in entries(kind))


@pytest.mark.parametrize("kind, name", [("bench", n) for n in sorted(BENCHES)] + [("compare", n) for n in sorted(EXPERIMENTS)])
def test_every_name_answers_its_help(capsys, kind, name):
    with pytest.raises(SystemExit) as exit:
        main([kind, name, "--help"])
    assert exit.value.code == 0
    assert f"usage: symkf {kind} {name}" in capsys.readouterr().out

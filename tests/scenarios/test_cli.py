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
    out = capsys.readouterr().out
    assert f"usage: symkf {kind} {name}" in out
    assert not re.search(r"issue \d|``|:\w+:`|/work/|shared/data", out), out


def test_version_is_the_installed_package_version(capsys):
    from importlib.metadata import version

    import symkf
    assert symkf.__version__ == version("symkf")
    with pytest.raises(SystemExit) as exit:
        main(["--version"])
    assert exit.value.code == 0
    assert capsys.readouterr().out.startswith(f"symkf {symkf.__version__} (CasADi ")


def test_help_of_the_top_package_names_its_sub_packages():
    import symkf
    for room in ("symkf.models", "symkf.codegen", "symkf.runtime", "symkf.scenarios"):
        assert room in symkf.__doc__


def test_options_lists_every_codegen_option_with_type_default_and_meaning(capsys):
    from symkf.codegen.spec import codegen_options
    assert main(["options"]) == 0
    out = capsys.readouterr().out
    listed = dict(re.findall(r"^(\w+)  \((.+)\)$", out, flags=re.M))
    options = codegen_options()
    assert set(listed) == {o.name for o in options} and len(options) > 40
    for o in options:
        assert listed[o.name].startswith(o.type_name + ", default ") and len(o.meaning) > 20, o.name
    assert main(["options", "--markdown"]) == 0
    table = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| `")]
    assert len(table) == len(options)


def test_families_lists_every_registered_family_with_x0_P0_Q(capsys):
    from symkf.codegen.families.framework import FAMILIES
    from symkf.scenarios.cli_reference import FAMILY_GUIDE
    assert set(FAMILY_GUIDE) == set(FAMILIES)
    assert main(["families"]) == 0
    out = capsys.readouterr().out
    blocks = re.split(r"^(?=\w+  \(filters: )", out, flags=re.M)[1:]
    assert {block.split()[0] for block in blocks} == set(FAMILIES)
    for block in blocks:
        for label in ("x0: ", "P0: ", "Q:  ", "cost: "):
            assert label in block, (block.split()[0], label)


def test_build_help_lists_the_paper_models_and_points_to_options(capsys):
    from symkf.models import PAPER_MODELS
    with pytest.raises(SystemExit) as exit:
        main(["build", "--help"])
    assert exit.value.code == 0
    out = capsys.readouterr().out
    for name in PAPER_MODELS:
        assert re.search(rf"^  {name} +\S", out, flags=re.M), name
    assert "symkf options" in out


@pytest.mark.parametrize("argv", [["--help"], ["build", "--help"], ["options"], ["families"]])
def test_help_texts_speak_to_users(capsys, argv):
    try:
        main(argv)
    except SystemExit:
        pass
    out = capsys.readouterr().out
    assert out and not re.search(r"issue \d|\b[0-9a-f]{7,40}\b|``|/work/|shared/data", out), out



def test_the_family_guide_says_what_the_filters_take(tmp_path, write_model):
    """What ``symkf families`` says P0 is, checked on built filters: n x n for the EKF of an ordinary
    model, n_error x n_error (3 per quaternion) for the MEKF and the manifold UKF; the wrong size
    is refused."""
    from pathlib import Path

    import numpy as np

    from symkf.runtime import load
    from symkf.scenarios.cli_reference import FAMILY_GUIDE
    assert FAMILY_GUIDE["ekf"].P0.startswith("n x n")
    tiny = load(write_model(tmp_path / "tiny.py"))
    assert tiny.ekf([0.0, 1.0], np.eye(2), np.eye(2) * 1e-3).P.shape == (2, 2)
    spinner = load(str(Path(__file__).resolve().parents[1] / "codegen" / "spinner_model.py"))
    n, n_error = len(spinner.model["states"]), spinner.model["error_state_dim"]
    assert n_error == n - 1                                   # one quaternion: 4 numbers in x, 3 in P
    q0 = np.array([0.0, 0.0, 0.0, 1.0, *np.zeros(n - 4)])
    for family in ("mekf", "mukf"):
        assert "n_error x n_error" in FAMILY_GUIDE[family].P0
        f = spinner.filter(family, q0, np.eye(n_error) * 1e-2, np.eye(n_error) * 1e-6)
        assert f.P.shape == (n_error, n_error) and f.x.shape == (n,)
        with pytest.raises(ValueError):
            spinner.filter(family, q0, np.eye(n) * 1e-2, np.eye(n_error) * 1e-6)     # an n x n P0 is refused

"""Degenerate models are refused at validate() with one line: no state, no measurement, and sizes
past the documented limits (models/checks.py MAX_STATES, MAX_OUTPUTS), which an environment
variable raises on purpose; `symkf build` says the same line, builds nothing."""
import time

import pytest

from symkf.models import Model, ModelError, get_model
from symkf.models import checks
from symkf.scenarios.cli import main

NO_MEASUREMENT = '''
from symkf.models import Model


def build():
    m = Model("drift", "a state and no sensor", paper="none")
    x = m.state("x", "m", "position")
    m.set_dynamics({"x": -0.1 * x})
    m.filters = ("ekf", "ukf")
    return m
'''


def chain(n: int, outputs: int = 1) -> Model:
    """n states in a chain, the first ``outputs`` of them measured."""
    m = Model("chain", "a chain of first-order lags", paper="none")
    xs = [m.state(f"x{i}", "m", "link") for i in range(n)]
    m.set_dynamics({f"x{i}": -xs[i] + (xs[i + 1] if i + 1 < n else 0) for i in range(n)})
    m.measurement("z", [(f"z{i}", "m", "link", xs[i]) for i in range(outputs)], sigma=[1.0] * outputs)
    return m


def _one_line(info) -> str:
    text = str(info.value)
    assert "\n" not in text
    return text


def test_zero_states_is_refused_in_one_line():
    m = Model("empty", "nothing", paper="none")
    with pytest.raises(ModelError, match="no states declared") as info:
        m.set_dynamics({})
    assert "declare them with model.state" in _one_line(info)


def test_no_measurement_is_refused_at_validate_and_by_the_cli(tmp_path, capsys, monkeypatch):
    path = tmp_path / "drift.py"
    path.write_text(NO_MEASUREMENT)
    with pytest.raises(ModelError, match="no measurement declared") as info:
        get_model(str(path))
    assert "model.measurement(" in _one_line(info)
    monkeypatch.setenv("SYMKF_BUILD_DIR", str(tmp_path / "build"))
    assert main(["build", str(path)]) == 1
    err = capsys.readouterr().err
    assert err.startswith("symkf build: model 'drift': no measurement declared") and err.count("\n") == 1
    assert not (tmp_path / "build").exists()


def test_too_many_states_is_refused_at_once_with_the_override_named(monkeypatch):
    monkeypatch.delenv("SYMKF_MAX_STATES", raising=False)
    big = chain(2_000)
    start = time.perf_counter()
    with pytest.raises(ModelError) as info:
        big.validate()
    assert time.perf_counter() - start < 5                     # refused first, before any check or generation
    text = _one_line(info)
    assert "2000 states is past the limit of 48" in text and "SYMKF_MAX_STATES=2000" in text
    chain(checks.MAX_STATES).validate()                        # at the limit: fine
    monkeypatch.setenv("SYMKF_MAX_STATES", "60")
    chain(60).validate()                                       # raised on purpose
    monkeypatch.setenv("SYMKF_MAX_STATES", "many")
    with pytest.raises(ModelError, match="SYMKF_MAX_STATES='many': expected an integer >= 1"):
        chain(3).validate()


def test_a_measurement_with_too_many_outputs_is_refused(monkeypatch):
    monkeypatch.delenv("SYMKF_MAX_OUTPUTS", raising=False)
    monkeypatch.setenv("SYMKF_MAX_STATES", "49")
    with pytest.raises(ModelError, match="measurement 'z' has 49 outputs, past the limit of 48") as info:
        chain(49, outputs=49).validate()
    assert "SYMKF_MAX_OUTPUTS=49" in _one_line(info)
    monkeypatch.setenv("SYMKF_MAX_OUTPUTS", "49")
    chain(49, outputs=49).validate()


@pytest.mark.parametrize("name", ["launcher", "attitude", "geo_satellite", "marg", "marg_mekf"])
def test_the_paper_models_are_within_the_limits(name):
    model = get_model(name)
    assert 0 < model.nx <= checks.MAX_STATES and model.measurements

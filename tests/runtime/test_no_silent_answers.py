"""No silent wrong answers: every call a careless user could get wrong is an error (x, P, t
unchanged) or a said choice, tried on a new user's two-sensor attitude model (sun sensor +
magnetometer, gyro input; tests/runtime/two_sensor_model.py) and on the launcher.

- a model with two measurements: a step without the measurement's name;
- a model with inputs: a step without u (u="hold" keeps the last input, said on purpose);
- a t that is not the filter's time (a jump ahead, a step backwards);
- a run with refused steps (raises by default, the result attached; refused="continue" counts);
- a gross outlier (the default chi-square gate refuses it; gate="none" fuses it);
- a plain EKF/UKF on a quaternion state (refused at build unless the model says so);
- what the filter says it is (repr with states, units and P's chart; R as a mapping) and the
  generated files' pointer to the model's real source.
"""
from __future__ import annotations

import inspect
import re
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import symkf.runtime as runtime
from symkf.codegen import BuildError, generate
from symkf.codegen.spec import STATUS_GATED
from symkf.models import Model, get_model
from symkf.runtime import DEFAULT_GATE_PROBABILITY, RunRefused, load

MODEL = str(Path(__file__).resolve().parent / "two_sensor_model.py")
SUN, FIELD = np.array([0.6, 0.0, 0.8]), np.array([0.0, 0.8, -0.6])
GYRO = np.array([0.02, -0.01, 0.005])
DT = 0.1


@pytest.fixture(scope="module")
def sun_mag():
    return load(MODEL)


def make(compiled, family="mekf", **options):
    x0 = np.r_[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]
    P0 = np.diag([1e-2] * 3 + [1e-6] * 3)
    Q = np.diag([1e-6] * 3 + [1e-10] * 3)
    return compiled.filter(family, x0, P0, Q, **options)


def snapshot(f):
    return f.x.copy(), f.P.copy(), f.t


def assert_unchanged(f, before):
    x, P, t = before
    assert np.array_equal(f.x, x) and np.array_equal(f.P, P) and f.t == t


def body(q, vector):
    """A reference-frame unit vector seen in the body of attitude q (scalar-last)."""
    return Rotation.from_quat(q).inv().apply(vector)


def raises(f, call, match: str):
    before = snapshot(f)
    with pytest.raises(ValueError, match=match):
        call()
    assert_unchanged(f, before)


# ---------------------------------------------------------------------- what the user must say
@pytest.mark.parametrize("family", ["mekf", "mukf"])
def test_a_measurement_must_be_named_when_the_model_has_two(sun_mag, family):
    f = make(sun_mag, family)
    f.step(0.0, DT, SUN, "sun", u=GYRO)
    raises(f, lambda: f.step(f.t, DT, FIELD, u=GYRO), r"measurements \['sun', 'mag'\]; name the one z is")
    raises(f, lambda: f.run(f.t + DT * np.arange(1, 4), np.tile(FIELD, (3, 1)), u=GYRO), "name the one z is")
    with pytest.raises(ValueError, match="name the one z is"):
        f.y()
    assert f.step(f.t, DT, body(f.x[:4], FIELD), "mag", u=GYRO) in (0, STATUS_GATED)


def test_an_input_must_be_given_or_held_on_purpose(sun_mag):
    f = make(sun_mag)
    raises(f, lambda: f.step(0.0, DT, SUN, "sun"), r"inputs \['w_x \[rad/s\]'.*u=\.\.\. on every call")
    raises(f, lambda: f.step(0.0, DT, SUN, "sun", u="hold"), "none yet")       # nothing to hold yet
    raises(f, lambda: f.run([0.0, DT], np.tile(SUN, (2, 1)), "sun"), "u=")
    held, given = make(sun_mag), make(sun_mag)
    for filt in (held, given):
        filt.step(0.0, DT, SUN, "sun", u=GYRO)
    held.step(DT, DT, SUN, "sun", u="hold")
    given.step(DT, DT, SUN, "sun", u=GYRO)
    np.testing.assert_array_equal(held.x, given.x)
    np.testing.assert_array_equal(held.P, given.P)
    held.update(FIELD, "mag")              # an update evaluates h with the input of the interval before it
    given.update(FIELD, "mag", u=GYRO)
    np.testing.assert_array_equal(held.x, given.x)


def test_the_time_must_be_the_filters_clock(sun_mag):
    f = make(sun_mag)
    f.step(0.0, DT, SUN, "sun", u=GYRO)
    raises(f, lambda: f.step(5000.0, DT, SUN, "sun", u=GYRO), r"t = 5000.0, but the filter's time is 0.1 .*predict\(0.1, ")
    raises(f, lambda: f.step(-1e6, DT, SUN, "sun", u=GYRO), "does not step backwards")
    raises(f, lambda: f.update(SUN, "sun", t=3.0), "filter's time is 0.1")
    raises(f, lambda: f.run([0.05, 0.2], np.tile(SUN, (2, 1)), "sun", u=GYRO), "does not step backwards")
    for k in range(1, 20):                 # a caller's t0 + k dt agrees with the clock's sums
        f.step(k * DT, DT, body(f.x[:4], SUN), "sun", u=GYRO)
    f.predict(None, 5000.0 - f.t, u=GYRO)  # the gap, propagated on purpose
    assert f.step(5000.0, DT, body(f.x[:4], SUN), "sun", u=GYRO) in (0, STATUS_GATED)
    f.t = 0.0                              # or the clock restarted on purpose
    assert f.t == 0.0


def test_the_c_fast_path_declines_what_the_python_path_refuses(sun_mag):
    f = make(sun_mag)
    f.step(0.0, DT, SUN, "sun", u=GYRO)
    calls = f.fast_calls
    assert calls >= 1, "the fast path took the plain call"
    for bad in (lambda: f.step(9.0, DT, SUN, "sun", u=GYRO), lambda: f.step(DT, DT, SUN, "sun"),
                lambda: f.step(DT, DT, SUN, u=GYRO)):
        raises(f, bad, ".")
    assert f.fast_calls == calls


# ---------------------------------------------------------------------- failures are not quiet
def test_a_run_with_refused_steps_raises_with_its_result(sun_mag):
    f = make(sun_mag, gate="none")
    f.step(0.0, DT, SUN, "sun", u=GYRO)
    times = f.t + DT * np.arange(1, 7)
    z = np.tile(SUN, (6, 1))
    z[2] = z[4] = 1e200                   # overflows the update: SYMKF_ERR_NONFINITE, that step refused
    before = snapshot(f)
    with pytest.raises(RunRefused, match=r"2 of 6 steps refused \(SYMKF_ERR_NONFINITE: 2\), the first at step 2") as error:
        f.run(times, z, "sun", u=GYRO)
    assert_unchanged(f, before)
    assert error.value.steps.tolist() == [2, 4] and error.value.result.x.shape == (6, 7)
    result = f.run(times, z, "sun", u=GYRO, refused="continue")
    assert result.refused_steps.tolist() == [2, 4] and result.counts == {"SYMKF_ERR_NONFINITE": 2}
    assert "SYMKF_ERR_NONFINITE: 2; refused steps [2, 4]" in repr(result)
    np.testing.assert_array_equal(result.x, error.value.result.x)
    assert f.t == times[-1]


def test_a_gross_outlier_is_refused_by_the_default_gate(launcher_compiled):
    from symkf.models import launcher as L
    x0 = L.initial_state()
    P0 = np.diag([10.0, 1e-3, 1e-3, 1e3, 1e-5, 1e-5]) ** 2
    Q = np.diag([1.0, 1e-8, 1e-8, 1.0, 1e-14, 1e-14])
    guarded, open_ = launcher_compiled.ekf(x0, P0, Q), launcher_compiled.ekf(x0, P0, Q, gate="none")
    z = np.array([1e30, 0.3, 0.5])                 # a 1e30 m range
    assert DEFAULT_GATE_PROBABILITY == 1 - 1e-9
    before = snapshot(guarded)
    assert guarded.update(z, "radar", q=L.station_params(1)) == STATUS_GATED
    assert_unchanged(guarded, before)
    open_.update(z, "radar", q=L.station_params(1))
    sigmas = np.abs(open_.x - x0) / np.sqrt(np.diag(P0))
    assert sigmas.max() > 1e6, sigmas               # what the default protects a user from: fused
    from symkf.runtime.reference import ReferenceFilter
    exact = ReferenceFilter("launcher", "ekf", x0, P0, Q)._h("radar", 0.0, x0, L.station_params(1))
    times = np.array([0.0, 1e-3, 2e-3])
    with pytest.warns(RuntimeWarning, match="1 of 3 updates refused by the default innovation gate"):
        r = launcher_compiled.ekf(x0, P0, Q).run(times, np.array([exact, z, exact]), "radar", q=L.station_params(1))
    assert r.gated_steps == 1


# ---------------------------------------------------------------------- quaternion states
def _quaternion_model(filters, opt_in=()):
    m = Model("free_q", "a quaternion state asked of plain filters", paper="none")
    q = m.quaternion_state("q", "attitude")
    w = m.input("w", "rad/s", "rate about z")
    import casadi as ca
    from symkf.models import quaternion as quat
    m.set_dynamics({"q": 0.5 * quat.hamilton(q, ca.vertcat(0, 0, w, 0))})
    m.measurement("z", [("qz", "-", "z component", q[2])], sigma=[0.01])
    m.filters = filters
    m.quaternion_as_vector_families = opt_in
    return m


def test_plain_filters_on_a_quaternion_state_need_an_explicit_choice():
    with pytest.raises(BuildError, match=r"\['ekf', 'ukf'\] would treat quaternion state q as 4 free states.*'mekf'"):
        generate(get_model(_quaternion_model(("ekf", "ukf"))))
    bundle = generate(get_model(_quaternion_model(("ekf",), opt_in=("ekf",))))
    assert [f.name for f in bundle.filters] == ["ekf"]


def test_the_filter_says_what_it_is(sun_mag):
    f = make(sun_mag)
    text = repr(f)
    assert "b_x = 0 [rad/s]" in text and "rotation vector dtheta [rad]" in text and "6 x 6" in text
    assert set(f.R) == {"sun", "mag"} and np.allclose(np.diag(f.R["mag"]), 0.03 ** 2)
    before = f.R["sun"].copy()
    with pytest.raises(ValueError, match="not positive definite"):
        f.R = {"sun": np.eye(3), "mag": -np.eye(3)}            # checked first: nothing written
    np.testing.assert_array_equal(f.R["sun"], before)
    f.R = {"sun": 4 * before}
    np.testing.assert_array_equal(f.R["sun"], 4 * before)
    with pytest.raises(TypeError):
        f.R["sun"] = before                                    # a mapping the user reads, not writes


def test_generated_files_name_the_models_real_source(sun_mag):
    folder = Path(sun_mag.build.directory)
    for name in ("two_sensor.h", "Makefile"):
        text = (folder / name).read_text()
        assert f"Generated by symkf from {MODEL}" in text and f"`symkf build {MODEL}`" in text
        assert "models/two_sensor.py" not in text
    assert "models/launcher.py" in (Path(load("launcher").build.directory) / "launcher.h").read_text()


# ---------------------------------------------------------------------- docstrings name what exists


@pytest.mark.parametrize("obj", [runtime.Filter, runtime.CompiledModel, Model, runtime.load])
def test_docstrings_name_methods_that_exist(obj):
    """Every ``filter.name(``/``model.name(`` a docstring of the public API shows exists."""
    owners = {"filter": runtime.Filter, "f": runtime.Filter, "model": Model, "m": Model, "compiled": runtime.CompiledModel}
    texts = [inspect.getdoc(obj) or ""] + [inspect.getdoc(v) or "" for v in vars(obj).values() if callable(v)] \
        if inspect.isclass(obj) else [inspect.getdoc(obj) or ""]
    missing = []
    for text in texts:
        for match in re.finditer(r"\b(filter|f|model|m|compiled)\.([a-z_]+)\(", text):
            owner, name = owners[match.group(1)], match.group(2)
            if not hasattr(owner, name):
                missing.append(f"{match.group(1)}.{name}")
    assert not missing, missing

"""The step fast path (runtime/_fastcall.c): same numbers as the Python path, and it declines,
writing nothing, every call it is not sure of (the contract itself is tests/test_contract.py)."""
import os
import subprocess
import sys

import numpy as np
import pytest

from symkf.runtime import SymkfError, fastcall, load
from symkf.scenarios.attitude.filter import attitude_filter
from symkf.scenarios.marg.filter import make_filter
from symkf.scenarios.launcher.truth import propagate, radar_track
from symkf.scenarios.marg import mekf
from symkf.scenarios.marg.data import Recording

P0 = np.diag([10.0, 1e-4, 1e-4, 1000.0, 1e-5, 1e-5]) ** 2
Q = np.diag([1.0, 1e-8, 1e-8, 1.0, 1e-14, 1e-14])
TIMES = np.arange(13) * 0.05
TRUTH = propagate(TIMES)
X0 = TRUTH[0] + np.array([10.0, 1e-8, 1e-8, 1000.0, 1e-8, 1e-8])
_TRACK = radar_track(TIMES, TRUTH)
Z, STATIONS = _TRACK.noisy(np.random.default_rng(7)), _TRACK.station_params()
STATION = STATIONS[1]

pytestmark = pytest.mark.skipif(fastcall.extension() is None, reason=f"no fast path: {fastcall.unavailable}")


@pytest.fixture(scope="module")
def marg():
    return load("marg", backend="compiled")


def _radar(k: int) -> np.ndarray:
    return Z[k].copy()


def _python_path(f):
    """The same filter with the fast path switched off (every call through runtime/contract.py)."""
    f.fast_path = False
    assert not f.fast_path
    return f


def _state(f) -> tuple:
    return f.x.copy(), (f.P.copy() if "P" in f._buffers else None), f.t


@pytest.mark.parametrize("family", ["ekf", "ukf"])
def test_launcher_fast_path_equals_python_path_bit_for_bit(launcher_compiled, family):
    fast = launcher_compiled.filter(family, X0, P0, Q)
    slow = _python_path(launcher_compiled.filter(family, X0, P0, Q))
    assert fast.fast_path and fast._fast.steps["radar"] is not None
    masks = [None, np.array([1.0, 0.0, 1.0]), None, np.array([0.0, 0.0, 0.0]), None]
    for k in range(1, len(TIMES)):
        mask = masks[k % len(masks)]
        codes = [f.step(TIMES[k - 1], 0.05, Z[k], "radar", q=STATIONS[k], mask=mask) for f in (fast, slow)]
        assert codes[0] == codes[1] == 0
        for a, b in zip(_state(fast), _state(slow)):
            assert np.array_equal(a, b)
        assert np.array_equal(fast.y("radar"), slow.y("radar")) and np.array_equal(fast.S("radar"), slow.S("radar"))
        assert np.array_equal(fast.kernel_buffer("mask", "radar"), slow.kernel_buffer("mask", "radar"))
    assert type(fast.t) is float and fast.t == slow.t


@pytest.mark.parametrize("form", ["simple", "full"])
def test_marg_fast_path_equals_python_path(marg, form):
    rng = np.random.default_rng(3)
    fast, slow = make_filter(marg, form), _python_path(make_filter(marg, form))
    for k in range(50):
        gyro, acc, mag = rng.normal(0, 0.2, 3), rng.normal([0, 0, 9.8], 0.5), rng.normal([20, 0, -40], 2)
        mask = np.r_[np.ones(3), np.zeros(3) if k % 7 == 0 else np.ones(3)]   # a missing magnetometer sample
        t = fast.t
        codes = [f.step(t, 0.01, np.r_[acc, mag], "marg", mask=mask, u=gyro) for f in (fast, slow)]
        assert codes == [0, 0] and np.array_equal(fast.x, slow.x) and fast.t == slow.t
    assert fast.fast_calls == 50 and slow.fast_calls == 0 and not fast.x.flags.writeable


def test_attitude_fast_path_equals_python_path():
    fast, slow = (attitude_filter("mekf", [0, 0, 0, 1.0], np.zeros(3), np.eye(6) * 1e-4, backend="compiled")
                  for _ in range(2))
    _python_path(slow)
    q_s = np.array([0.01, 0.0, 0.0, np.sqrt(1 - 1e-4)])
    for k in range(5):
        codes = [f.step(np.array([1e-3, 0.0, 2e-3]), 0.1, q_s) for f in (fast, slow)]
        assert codes == [0, 0]
        for a, b in zip(_state(fast), _state(slow)):
            assert np.array_equal(a, b)


def _buffers(f) -> list[np.ndarray]:
    return [b.copy() for b in f._buffers.values()] + [b.copy() for m in f.measurements.values() for b in m.values()]


BIG_ENDIAN = np.array([1000.0, 0.3, 0.2], dtype=">f8")
#: (t, dt, z, q, mask, u) calls the C fast path must hand to the Python contract.
DECLINED = {
    "t string": ("0", 0.05, _radar(1), STATION, None, None),
    "t NaN": (np.nan, 0.05, _radar(1), STATION, None, None),
    "t int": (0, 0.05, _radar(1), STATION, None, None),
    "t float32": (np.float32(0.0), 0.05, _radar(1), STATION, None, None),
    "t 0-d array": (np.array(0.0), 0.05, _radar(1), STATION, None, None),
    "dt zero": (0.0, 0.0, _radar(1), STATION, None, None),
    "dt negative": (0.0, -0.05, _radar(1), STATION, None, None),
    "dt inf": (0.0, np.inf, _radar(1), STATION, None, None),
    "dt bool": (0.0, True, _radar(1), STATION, None, None),
    "z list short": (0.0, 0.05, [1000.0, 0.3], STATION, None, None),
    "z list with a bool": (0.0, 0.05, [1000.0, True, 0.2], STATION, None, None),
    "z list with a string": (0.0, 0.05, [1000.0, "0.3", 0.2], STATION, None, None),
    "z list with float32": (0.0, 0.05, [1000.0, np.float32(0.3), 0.2], STATION, None, None),
    "z list nested": (0.0, 0.05, [[1000.0, 0.3, 0.2]], STATION, None, None),
    "z list NaN": (0.0, 0.05, [1000.0, float("nan"), 0.2], STATION, None, None),
    "z list huge int": (0.0, 0.05, [10 ** 400, 0.3, 0.2], STATION, None, None),
    "mask list half": (0.0, 0.05, _radar(1), STATION, [1, 0.5, 1], None),
    "z short": (0.0, 0.05, _radar(1)[:2], STATION, None, None),
    "z column": (0.0, 0.05, _radar(1).reshape(3, 1), STATION, None, None),
    "z float32": (0.0, 0.05, _radar(1).astype(np.float32), STATION, None, None),
    "z int": (0.0, 0.05, np.array([1000, 0, 0]), STATION, None, None),
    "z complex": (0.0, 0.05, _radar(1) + 0j, STATION, None, None),
    "z NaN": (0.0, 0.05, np.array([np.nan, 0.3, 0.2]), STATION, None, None),
    "z NaN used": (0.0, 0.05, np.array([1000.0, np.nan, 0.2]), STATION, np.array([1.0, 1.0, 0.0]), None),
    "z Inf": (0.0, 0.05, np.array([1000.0, np.inf, 0.2]), STATION, None, None),
    "z big-endian": (0.0, 0.05, BIG_ENDIAN, STATION, None, None),
    "z object": (0.0, 0.05, np.array([1.0, 2.0, 3.0], dtype=object), STATION, None, None),
    "z None": (0.0, 0.05, None, STATION, None, None),
    "z bytes": (0.0, 0.05, b"\0" * 24, STATION, None, None),
    "q missing": (0.0, 0.05, _radar(1), None, None, None),
    "q long": (0.0, 0.05, _radar(1), np.zeros(3), None, None),
    "mask half": (0.0, 0.05, _radar(1), STATION, np.array([1.0, 0.5, 1.0]), None),
    "mask two": (0.0, 0.05, _radar(1), STATION, np.array([1.0, 2.0, 1.0]), None),
    "mask NaN": (0.0, 0.05, _radar(1), STATION, np.array([1.0, np.nan, 1.0]), None),
    "mask bool": (0.0, 0.05, _radar(1), STATION, np.array([True, False, True]), None),
    "u given": (0.0, 0.05, _radar(1), STATION, None, np.zeros(1)),
}


@pytest.mark.parametrize("case", sorted(DECLINED))
def test_fast_path_declines_and_writes_nothing(launcher_compiled, case):
    f = launcher_compiled.ekf(X0, P0, Q)
    before = _buffers(f)
    assert f._fast.steps["radar"](*DECLINED[case]) is None
    assert all(np.array_equal(a, b, equal_nan=True) for a, b in zip(before, _buffers(f)))


def test_what_the_python_path_accepts_the_fast_path_takes_alike(launcher_compiled):
    """t None (the filter's time) and a NaN in a component the mask leaves out (never read by the
    kernel): accepted by the contract, so taken by the fast path with the very same result."""
    z = np.array([Z[1][0], np.nan, Z[1][2]])
    fast, slow = launcher_compiled.ekf(X0, P0, Q), _python_path(launcher_compiled.ekf(X0, P0, Q))
    for f in (fast, slow):
        f.t = TIMES[0]
        assert f.step(None, 0.05, z, "radar", q=STATION, mask=np.array([1.0, 0.0, 1.0])) == 0
    assert fast.fast_calls == 1 and slow.fast_calls == 0
    for a, b in zip(_state(fast), _state(slow)):
        assert np.array_equal(a, b)
    assert fast.t == slow.t == TIMES[0] + 0.05
    assert np.array_equal(fast.kernel_buffer("z", "radar"), z, equal_nan=True)


def test_lists_and_tuples_of_numbers_take_the_fast_path_alike(launcher_compiled):
    """Plain Python sequences (floats, ints; a mask of ints) are read in C exactly as the Python
    path converts them: the same state, bit for bit."""
    fast, slow = launcher_compiled.ekf(X0, P0, Q), _python_path(launcher_compiled.ekf(X0, P0, Q))
    for f in (fast, slow):
        for k in range(1, 4):
            z = [float(v) for v in Z[k]]
            z[0] = int(z[0])                                           # an int among floats
            assert f.step(TIMES[k - 1], 0.05, z, "radar", q=tuple(STATIONS[k]), mask=[1, 1, 1]) == 0
    assert fast.fast_calls == 3 and slow.fast_calls == 0
    for a, b in zip(_state(fast), _state(slow)):
        assert np.array_equal(a, b)


def test_the_fast_path_counts_only_the_calls_it_took(launcher_compiled):
    f = launcher_compiled.ekf(X0, P0, Q)
    f.step(TIMES[0], 0.05, Z[1], "radar", q=STATION)
    f.step(TIMES[1], 0.05, Z[2].astype(">f8"), "radar", q=STATIONS[2])        # big-endian: the Python path
    with pytest.raises(ValueError):
        f.step(TIMES[2], 0.05, Z[3], "radar", q=STATIONS[3], mask=np.array([1.0, 0.5, 1.0]))
    assert f.fast_calls == 1
    f.fast_path = False
    f.step(TIMES[2], 0.05, Z[3], "radar", q=STATIONS[3])
    assert f.fast_calls == 0 and not f.fast_path


def test_rows_of_a_column_major_record_take_the_fast_path(launcher_compiled):
    """A row of a Fortran-ordered (N, 3) array (a .mat file's layout) is a strided buffer."""
    z, q = np.asfortranarray(Z), np.asfortranarray(STATIONS)
    fast, slow = launcher_compiled.ekf(X0, P0, Q), _python_path(launcher_compiled.ekf(X0, P0, Q))
    for k in range(1, 4):
        assert fast._fast.steps["radar"](TIMES[k - 1], 0.05, z[k], q[k], None, None) == 0     # taken, not declined
        fast.t = TIMES[k]
        slow.step(TIMES[k - 1], 0.05, Z[k], "radar", q=STATIONS[k])
        assert np.array_equal(fast.x, slow.x) and np.array_equal(fast.P, slow.P)


def test_other_float64_buffers_take_the_fast_path(launcher_compiled):
    """Not only ndarrays: any native float64 buffer (array.array, memoryview) is read the same."""
    import array
    fast, slow = launcher_compiled.ekf(X0, P0, Q), _python_path(launcher_compiled.ekf(X0, P0, Q))
    assert fast._fast.steps["radar"](TIMES[0], 0.05, array.array("d", Z[1]), memoryview(STATIONS[1]), None, None) == 0
    slow.step(TIMES[0], 0.05, Z[1], "radar", q=STATIONS[1])
    assert np.array_equal(fast.x, slow.x) and np.array_equal(fast.P, slow.P)


def test_fast_path_checks_its_own_call(launcher_compiled):
    fast = launcher_compiled.ekf(X0, P0, Q)._fast.steps["radar"]
    with pytest.raises(TypeError, match="positional"):
        fast(0.0, 0.05, _radar(1))
    with pytest.raises(TypeError):
        fast(0.0, 0.05, _radar(1), STATION, None, u=None)


def test_a_kernel_failure_is_raised_by_the_python_path_with_state_unchanged(launcher_compiled):
    f = launcher_compiled.ekf(X0, P0, Q)
    f.kernel_buffer("P")[0, 0] = -1.0            # behind the contract's back: the C EKF refuses it
    before = _state(f)
    with pytest.raises(SymkfError, match="NOT_PD"):
        f.step(0.0, 0.05, _radar(1), "radar", q=STATION)
    assert all(np.array_equal(a, b) for a, b in zip(before, _state(f)))


def test_without_the_extension_every_call_takes_the_python_path(tmp_path):
    code = ("import numpy as np; from symkf.runtime import fastcall, load\n"
            "from symkf.scenarios.marg.filter import make_filter\n"
            "m = make_filter(load('marg', backend='compiled'))\n"
            "m.step(0.0, 0.01, np.array([0, 0, 9.8, 20.0, 0, -40]), 'marg', u=np.zeros(3))\n"
            "print(fastcall.extension() is None, m.fast_calls == 0, fastcall.unavailable, list(m.x))")
    env = {**os.environ, "SYMKF_FASTCALL": "0"}
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.startswith("True True disabled by SYMKF_FASTCALL=0")


def _still_then_turning(n: int = 700, rate: float = 285.714) -> Recording:
    """A MARG recording: 2 s at rest (the gyro-at-rest measurement switches on after 1.5 s), then a
    turn about the vertical; noisy gyro, accelerometer and magnetometer (ENU field, dip 60 deg)."""
    rng = np.random.default_rng(11)
    time = np.arange(n) / rate
    gyro = rng.normal(0.0, 1e-3, (n, 3)) + np.where(time[:, None] > 2.0, [0.0, 0.0, 0.5], 0.0)
    acc = rng.normal([0.0, 0.0, 9.81], 0.02, (n, 3))
    mag = rng.normal([0.0, 25.0, -43.0], 0.3, (n, 3))
    return Recording("still_then_turning", time, gyro, acc, mag)


def test_the_marg_mekf_common_call_takes_the_fast_path():
    """models/marg_mekf.py as scenarios/marg/mekf.py feeds it: 7 components (acc direction, heading,
    gyro at rest) with per-sample masks, the magnetometer as q, the gyro as u, rows of column-major
    records. Every call takes the fast path, with the Python path's numbers bit for bit."""
    compiled = load("marg_mekf", backend="compiled")
    recording = _still_then_turning()
    z, mask = np.asfortranarray(mekf.measurements(recording)), np.asfortranarray(mekf.masks(recording))
    z[mask == 0] = np.nan                           # masked out: never read, taken all the same
    mag, gyro, dt = np.asfortranarray(recording.mag), np.asfortranarray(recording.gyro), recording.dt
    fast, slow = mekf.make_filter(compiled, recording), _python_path(mekf.make_filter(compiled, recording))
    assert 0 < mask[:, 4].sum() < len(recording) - 1         # both states of the rest mask are met
    for k in range(1, len(recording)):
        for f in (fast, slow):
            assert f.step(recording.time[k - 1], dt[k], z[k], "marg", q=mag[k], mask=mask[k], u=gyro[k]) == 0
    assert fast.fast_calls == len(recording) - 1 and slow.fast_calls == 0
    for a, b in zip(_state(fast), _state(slow)):
        assert np.array_equal(a, b)


# ---------------------------------------------------------------------- the step method in C
def test_plain_step_calls_run_in_c_by_position_or_keyword(launcher_compiled):
    """``f.step`` is the C Method: every plain spelling of the call (positional, keywords, the
    measurement named) is taken by it (its own counter), with the Python path's numbers bit for bit."""
    fast, slow = launcher_compiled.ekf(X0, P0, Q), _python_path(launcher_compiled.ekf(X0, P0, Q))
    assert type(fast.step).__name__ == "Method" and type(slow.step).__name__ == "method"
    calls = [lambda f, k: f.step(TIMES[k - 1], 0.05, Z[k], "radar", q=STATIONS[k]),
             lambda f, k: f.step(TIMES[k - 1], 0.05, Z[k], "radar", STATIONS[k], np.ones(3)),
             lambda f, k: f.step(z=Z[k], dt=0.05, t=TIMES[k - 1], q=STATIONS[k], nan="raise", measurement="radar"),
             lambda f, k: f.step(None, 0.05, Z[k], measurement="radar", q=STATIONS[k], mask=[1, 0, 1], u=None)]
    for k in range(1, 9):
        assert calls[k % 4](fast, k) == calls[k % 4](slow, k) == 0
        for a, b in zip(_state(fast), _state(slow)):
            assert np.array_equal(a, b)
    assert fast.step.calls == 8 and fast.fast_calls == 8 and slow.fast_calls == 0


#: Calls the C Method hands to the Python method (which accepts or refuses them as before).
TO_PYTHON = {
    "nan mask": (dict(nan="mask"), None),
    "unknown keyword": (dict(bogus=1), TypeError),
    "measurement not a name": (dict(measurement=3), ValueError),
    "unknown measurement": (dict(measurement="sonar"), ValueError),
    "nan policy unknown": (dict(nan="ignore"), ValueError),
    "z missing": (dict(z=None), ValueError),
}


@pytest.mark.parametrize("case", sorted(TO_PYTHON))
def test_the_step_method_hands_other_calls_to_python(launcher_compiled, case):
    kwargs, error = TO_PYTHON[case]
    f, slow = launcher_compiled.ekf(X0, P0, Q), _python_path(launcher_compiled.ekf(X0, P0, Q))
    call = {"t": 0.0, "dt": 0.05, "z": Z[1], "measurement": "radar", "q": STATION, **kwargs}
    before = _state(f)
    if error is None:
        assert f.step(**call) == slow.step(**call)
        for a, b in zip(_state(f), _state(slow)):
            assert np.array_equal(a, b)
        assert f.step.calls == 0 and f.fast_calls == 0
    else:
        with pytest.raises(error) as caught:
            f.step(**call)
        with pytest.raises(error) as expected:
            slow.step(**call)
        assert str(caught.value) == str(expected.value)
        assert all(np.array_equal(a, b) for a, b in zip(before, _state(f))) and f.step.calls == 0


def test_the_step_method_takes_any_measurement_with_a_fast_path(launcher_compiled):
    fast, slow = (launcher_compiled.ekf(X0, P0, Q, gate="none"),
                  _python_path(launcher_compiled.ekf(X0, P0, Q, gate="none")))   # z is radar 1's: off this frame
    q = np.zeros(fast.kernel_buffer("q", "radar_wgs84").size)
    q[:STATION.size] = STATION
    assert fast.step(0.0, 0.05, Z[1], "radar_wgs84", q) == slow.step(0.0, 0.05, Z[1], "radar_wgs84", q) == 0
    assert fast.step.calls == 1
    for a, b in zip(_state(fast), _state(slow)):
        assert np.array_equal(a, b)


def test_the_step_method_keeps_python_s_errors_for_bad_arity(launcher_compiled):
    f = launcher_compiled.ekf(X0, P0, Q)
    with pytest.raises(TypeError, match="missing 1 required positional argument: 'z'"):
        f.step(0.0, 0.05)
    with pytest.raises(TypeError, match="multiple values for argument 't'"):
        f.step(0.0, 0.05, Z[1], "radar", t=0.0, q=STATION)
    with pytest.raises(TypeError, match="positional arguments"):
        f.step(0.0, 0.05, Z[1], "radar", STATION, None, None, "raise", 9)
    assert f.step.calls == 0 and f.t == 0.0


def test_gradient_descent_step_takes_the_fast_path_and_refuses_a_bool(marg):
    f = make_filter(marg)
    assert f.step(0.0, 0.01, np.array([0.0, 0.0, 9.8, 20.0, 0.0, -40.0]), "marg", u=np.zeros(3)) == 0
    assert f.step.calls == 1 and not f.x.flags.writeable
    f.step(f.t, dt=0.01, z=np.array([0.0, 0.0, 9.8]), measurement="imu", u=np.array([0.0, 0.0, 0.1]))
    assert f.step.calls == 2
    with pytest.raises(ValueError):
        f.step(f.t, 0.01, [0.0, 0.0, 9.8], "imu", u=[0.0, True, 0.0])       # a bool in a list: refused
    assert f.step.calls == 2 and f.fast_calls == 2


def test_attitude_step_method_predicts_through_python_without_a_sample():
    f = attitude_filter("mekf", [0, 0, 0, 1.0], np.zeros(3), np.eye(6) * 1e-4, backend="compiled")
    q_s = np.array([0.01, 0.0, 0.0, np.sqrt(1 - 1e-4)])
    assert f.step(np.array([1e-3, 0.0, 2e-3]), 0.1, q_s) == 0 and f.fast_calls == 1
    assert f.step(np.array([1e-3, 0.0, 2e-3]), 0.1) == 0 and f.fast_calls == 1       # q_s None: predict
    assert f.t == pytest.approx(0.2)


def test_a_subclass_s_own_step_is_not_replaced(launcher_compiled):
    from symkf.runtime.filters import Filter

    class Logged(Filter):
        def step(self, *args, **kwargs):
            self.logged = True
            return super().step(*args, **kwargs)

    f = Logged(launcher_compiled, "ekf", X0, P0, Q)
    assert "step" not in f.__dict__
    assert f.step(0.0, 0.05, Z[1], "radar", q=STATION) == 0 and f.logged and f.fast_calls == 1


def test_the_step_method_reads_each_call_site_s_keywords(launcher_compiled):
    """Method caches the parameters of the last keyword names it saw (a call site passes the same
    tuple every time): calls with other names, in another order, or an unknown name in between,
    still read each argument by its own name."""
    fast, slow = launcher_compiled.ekf(X0, P0, Q), _python_path(launcher_compiled.ekf(X0, P0, Q))
    spellings = [dict(measurement="radar", q=STATIONS[0], mask=None), dict(mask=None, q=STATIONS[0], measurement="radar"),
                 dict(bogus=1), dict(measurement="radar", q=STATIONS[0]), {"q": STATIONS[0], "measurement": "radar"}]
    for k in range(1, 11):
        kwargs = dict(spellings[k % len(spellings)])
        if "q" in kwargs:
            kwargs["q"] = STATIONS[k]
        results = []
        for f in (fast, slow):
            try:
                results.append(f.step(f.t, 0.05, Z[k], **kwargs))
            except TypeError as error:
                results.append(str(error))
        assert results[0] == results[1]
        for a, b in zip(_state(fast), _state(slow)):
            assert np.array_equal(a, b)
    assert fast.step.calls == 8

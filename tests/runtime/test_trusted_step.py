"""Filter.step's trusted kernel (runtime/fastpath.py, runtime/_fastcall.c): once a step has succeeded
and nothing was written from Python since, the fast path calls the run loop's trusted partner of
the step (no test of |q| = 1, P PSD or R diagonal, no y, S) and keeps the step's inputs; y() and
S() compute the diagnostics from them when asked. x, P, t, codes, y and S must be bit for bit those
of the checked kernel called every step (the Python path), through writes, failures and copies."""
import copy

import numpy as np
import pytest

from symkf.codegen.spec import STATUS_GATED
from symkf.runtime import SymkfError, fastcall, load
from symkf.scenarios.attitude.filter import attitude_filter
from symkf.scenarios.marg import mekf as ekf
from symkf.scenarios.marg.data import Recording

pytestmark = pytest.mark.skipif(fastcall.extension() is None, reason=f"no fast path: {fastcall.unavailable}")

STEPS = 400


@pytest.fixture(scope="module")
def compiled():
    return load("marg_mekf", backend="compiled")


@pytest.fixture(scope="module")
def recording():
    """At rest (gyro-at-rest rows used), then turning, with magnetic disturbances (heading masked)."""
    rng = np.random.default_rng(11)
    time = np.arange(STEPS) / 285.714
    gyro = rng.normal(0.0, 2e-3, (STEPS, 3)) + np.where(time[:, None] > 1.0, [0.3, -0.2, 0.8], 0.0)
    acc = rng.normal([0.0, 0.0, 9.81], 0.05, (STEPS, 3))
    mag = rng.normal([0.0, 25.0, -43.0], 0.3, (STEPS, 3))
    mag[200:210] *= 1.2
    mag[330:350] *= 1.2
    return Recording("synthetic", time, gyro, acc, mag)


class Feed:
    """The recording's samples as Filter.step arguments."""

    def __init__(self, recording):
        self.r, self.z, self.mask = recording, ekf.measurements(recording), ekf.masks(recording)

    def step(self, f, k: int, **change):
        args = {"z": self.z[k], "q": self.r.mag[k], "mask": self.mask[k], "u": self.r.gyro[k], **change}
        return f.step(f.t, self.r.time[k] - self.r.time[k - 1], args.pop("z"), "marg", **args)   # t: the clock


def _pair(compiled, recording, threshold: float | None = None):
    fast, slow = ekf.make_filter(compiled, recording), ekf.make_filter(compiled, recording)
    slow.fast_path = False
    for f in (fast, slow):
        f.set_gate("marg", threshold=threshold)
    return fast, slow


def _same(fast, slow) -> None:
    assert np.array_equal(fast.x, slow.x) and np.array_equal(fast.P, slow.P) and fast.t == slow.t
    assert np.array_equal(fast.y("marg"), slow.y("marg")) and np.array_equal(fast.S("marg"), slow.S("marg"))


def _trusted_calls(f) -> int:
    return f._fast.steps["marg"].trusted_calls


@pytest.mark.parametrize("threshold", [None, 0.01])
def test_trusted_steps_equal_checked_steps_bit_for_bit(compiled, recording, threshold):
    """Every mask pattern of the record (each a variant of the trusted kernel), gate off and on;
    y and S read every few steps (a replay each) and at the end (several steps left unread)."""
    fast, slow = _pair(compiled, recording, threshold)
    feed, codes = Feed(recording), []
    for k in range(1, STEPS):
        codes.append([feed.step(f, k) for f in (fast, slow)])
        assert np.array_equal(fast.x, slow.x) and np.array_equal(fast.P, slow.P)
        if k % 5 == 0:
            _same(fast, slow)
    _same(fast, slow)
    assert all(a == b for a, b in codes)
    assert _trusted_calls(fast) == STEPS - 2 and fast.fast_calls == STEPS - 1 and slow.fast_calls == 0
    if threshold is not None:                           # gated steps are successes: trusted after them too
        assert 0 < sum(a == STATUS_GATED for a, _ in codes) < len(codes) - 10


def test_every_write_from_python_replays_first_and_makes_the_next_step_checked(compiled, recording):
    """A setter after a trusted step: y, S are still that step's (computed before the write, with
    the R and Q it used); the next step is a checked one (it tests what was written)."""
    fast, slow = _pair(compiled, recording)
    feed = Feed(recording)
    writes = [lambda f: f.set_R("marg", f.R["marg"] * 4.0), lambda f: setattr(f, "Q", f.Q * 2.0),
              lambda f: setattr(f, "P", f.P * 1.5), lambda f: setattr(f, "x", f.x),
              lambda f: f.set_gate("marg", 0.999), lambda f: f.kernel_buffer("z", "marg"),
              lambda f: f.predict(f.t, 0.002, u=recording.gyro[0])]
    k = 1
    for write in writes:
        for _ in range(3):
            for f in (fast, slow):
                feed.step(f, k)
            k += 1
        trusted = _trusted_calls(fast)
        for f in (fast, slow):
            write(f)
        _same(fast, slow)
        feed.step(fast, k), feed.step(slow, k)
        k += 1
        assert _trusted_calls(fast) == trusted                # the step after a write: checked
        _same(fast, slow)


def test_a_failed_step_keeps_the_state_and_the_diagnostics_of_the_last_success(compiled, recording):
    """A used component that overflows the update (finite, so the fast path takes the call): the
    trusted kernel fails, the Python path raises; x, P, t and y, S stay those of the step before."""
    fast, slow = _pair(compiled, recording)
    feed = Feed(recording)
    for k in range(1, 20):
        feed.step(fast, k), feed.step(slow, k)
    state = fast.x.copy(), fast.P.copy(), fast.t
    huge = feed.z[20].copy()
    huge[0] = 1e308
    for f in (fast, slow):
        with pytest.raises(SymkfError):
            feed.step(f, 20, z=huge)
    assert np.array_equal(fast.x, state[0]) and np.array_equal(fast.P, state[1]) and fast.t == state[2]
    _same(fast, slow)
    for k in range(20, 40):
        feed.step(fast, k), feed.step(slow, k)
    _same(fast, slow)


def test_copies_carry_the_diagnostics_left_to_replay(compiled, recording):
    fast, slow = _pair(compiled, recording)
    feed = Feed(recording)
    for k in range(1, 10):
        feed.step(fast, k), feed.step(slow, k)
    clone, deep = fast.copy(), copy.deepcopy(fast)
    for k in range(10, 15):
        feed.step(fast, k)                              # the original moves on; the copies do not
    for f in (clone, deep):
        _same(f, slow)
    for k in range(10, 15):
        feed.step(clone, k), feed.step(slow, k)
    _same(clone, slow)
    _same(fast, slow)
    assert _trusted_calls(clone) == 5                   # a copy of a state only steps wrote: trusted too


def test_attitude_mekf_diagnostics_through_its_own_step(compiled):
    """Paper 000's MEKF takes the trusted kernel too; its y and S properties replay alike."""
    fast, slow = (attitude_filter("mekf", [0, 0, 0, 1.0], np.zeros(3), np.eye(6) * 1e-4, backend="compiled")
                  for _ in range(2))
    slow.fast_path = False
    rng = np.random.default_rng(5)
    for k in range(30):
        q_s = np.r_[rng.normal(0, 1e-3, 3), 1.0]
        q_s /= np.linalg.norm(q_s)
        assert [f.step(np.array([1e-3, 0.0, 2e-3]), 0.1, q_s) for f in (fast, slow)] == [0, 0]
        if k % 4 == 0:
            assert np.array_equal(fast.y, slow.y) and np.array_equal(fast.S, slow.S)
    assert np.array_equal(fast.x, slow.x) and np.array_equal(fast.P, slow.P)
    assert np.array_equal(fast.y, slow.y) and np.array_equal(fast.S, slow.S)
    assert fast._fast.steps["star_tracker"].trusted_calls == 29


def test_the_views_a_filter_hands_out_cannot_be_made_writeable(compiled, recording):
    """x and P change only through the filter's calls (the trusted kernel relies on it): numpy
    refuses to turn a view back into a writeable array."""
    f = ekf.make_filter(compiled, recording)
    Feed(recording).step(f, 1)
    for view in (f.x, f.P, f.y("marg"), f.S("marg"), f.R["marg"], f.Q):
        with pytest.raises(ValueError):
            view.flags.writeable = True
        with pytest.raises(ValueError):
            view[0] = 1.0


def test_diagnostics_the_checked_kernel_refuses_to_replay_are_nan(compiled, recording):
    """The one case a trusted step and a checked one part: a kept P that fails the PSD test (a P
    the filter made itself: never seen; here forced). y and S then say so (NaN), x and P stand."""
    f = ekf.make_filter(compiled, recording)
    feed = Feed(recording)
    for k in range(1, 5):
        feed.step(f, k)
    assert _trusted_calls(f) == 3
    f._fast.replays["marg"].buffers["P"][0, 0] = -1.0
    x, P = f.x.copy(), f.P.copy()
    assert np.isnan(f.y("marg")).all() and np.isnan(f.S("marg")).all()
    assert np.array_equal(f.x, x) and np.array_equal(f.P, P)

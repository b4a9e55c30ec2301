"""A filter's copy (``f.copy()``, ``copy.copy``, ``copy.deepcopy``) is a filter of its own at the
same state: the C calls are bound to its own buffers, so stepping one leaves the other as it was
(a copy that shared the original's buffers would move both), and the copy steps exactly as the
original would. A filter cannot be pickled (its calls hold pointers): the error says what to send."""
import copy
import pickle

import numpy as np
import pytest

from symkf.runtime import load
from symkf.scenarios.attitude.filter import attitude_filter
from symkf.scenarios.marg.filter import initial_orientation, make_filter
from symkf.scenarios.launcher.truth import propagate, radar_track

P0 = np.diag([10.0, 1e-4, 1e-4, 1000.0, 1e-5, 1e-5]) ** 2
Q = np.diag([1.0, 1e-8, 1e-8, 1.0, 1e-14, 1e-14])
TIMES = np.arange(6) * 0.05
TRUTH = propagate(TIMES)
_TRACK = radar_track(TIMES, TRUTH)
Z, STATIONS = _TRACK.noisy(np.random.default_rng(7)), _TRACK.station_params()
COPIES = {"method": lambda f: f.copy(), "copy.copy": copy.copy, "copy.deepcopy": copy.deepcopy}


def _state(f) -> list:
    return [f.x.copy(), f.P.copy() if "P" in f._buffers else None, f.t]


def _equal(a: list, b: list) -> bool:
    return all(np.array_equal(u, v) for u, v in zip(a, b))


def _check_copy(original, make_copy, step) -> None:
    """Step the copy: the original stays; then step the original alike: both are equal, bit for bit."""
    clone = make_copy(original)
    before = _state(original)
    assert _equal(_state(clone), before)
    step(clone)
    assert _equal(_state(original), before), "stepping the copy moved the original"
    assert not _equal(_state(clone), before)
    step(original)
    assert _equal(_state(original), _state(clone))


@pytest.mark.parametrize("how", COPIES)
@pytest.mark.parametrize("family", ["ekf", "ukf"])
def test_a_launcher_filter_s_copy_is_its_own(launcher_compiled, family, how):
    f = launcher_compiled.filter(family, TRUTH[0], P0, Q)
    f.set_gate("radar", probability=0.999)
    f.step(TIMES[0], 0.05, Z[1], "radar", q=STATIONS[1])

    def step(g):
        assert g.step(TIMES[1], 0.05, Z[2], "radar", q=STATIONS[2], mask=[1.0, 0.0, 1.0]) == 0
    _check_copy(f, COPIES[how], step)
    clone = COPIES[how](f)                                  # the gate is copied, not shared
    assert clone.step(f.t, 0.05, [1e308, 0.1, 0.1], "radar", q=STATIONS[3]) == 6     # SYMKF_GATED
    assert clone.fast_calls >= 1 and clone.t != f.t


@pytest.mark.parametrize("how", COPIES)
def test_a_madgwick_filter_s_copy_is_its_own(how):
    compiled = load("marg", backend="compiled")
    f = make_filter(compiled, "full")
    f.x = initial_orientation(compiled, [0.1, 0.2, 9.7, 20.0, 1.0, -40.0])
    _check_copy(f, COPIES[how], lambda g: g.step(g.t, 0.01, np.array([0.3, 0.2, 9.6, 21.0, 0.0, -40.0]), "marg",
                                                 u=np.array([0.1, -0.2, 0.3])))
    clone, q = COPIES[how](f), f.x.copy()
    clone.x = initial_orientation(compiled, [9.7, 0.0, 0.1, 0.0, 20.0, -40.0])
    assert np.array_equal(f.x, q) and not np.array_equal(clone.x, q)


@pytest.mark.parametrize("how", COPIES)
def test_a_quaternion_filter_s_copy_is_its_own(how):
    f = attitude_filter("mekf", [0, 0, 0, 1.0], np.zeros(3), np.eye(6) * 1e-4, backend="compiled")
    q_s = np.array([0.01, 0.0, 0.0, np.sqrt(1 - 1e-4)])
    _check_copy(f, COPIES[how], lambda g: g.step(np.array([1e-3, 0.0, 2e-3]), 0.1, q_s))


def test_a_filter_cannot_be_pickled_and_says_what_to_send(launcher_compiled):
    with pytest.raises(TypeError, match="send the model and the state"):
        pickle.dumps(launcher_compiled.filter("ekf", TRUTH[0], P0, Q))

"""The benches' timing helper: interleaved rounds, a count of calls per function, wall and thread
CPU seconds per call, rounds gathered from paths timed each its own way, the load average."""
import time

import pytest

from symkf.scenarios import timing


def test_interleaved_calls_every_function_once_per_round_in_turn():
    order = []
    samples = timing.interleaved({"a": lambda i: order.append(("a", i)), "b": lambda i: order.append(("b", i))},
                                 rounds=3)
    assert order == [("a", 0), ("b", 0), ("a", 1), ("b", 1), ("a", 2), ("b", 2)]
    assert len(samples["a"].wall) == len(samples["b"].cpu) == 3


def test_a_count_of_calls_per_function_divides_its_own_rounds():
    """A function sleeping 20 ms is 20 ms of wall time and almost no CPU per round; counted as
    4 calls a round, 5 ms of wall time per call. A busy loop's CPU time is most of its wall time."""
    def busy(i):
        end = time.thread_time() + 0.02
        while time.thread_time() < end:
            pass
    samples = timing.interleaved({"sleep": lambda i: time.sleep(0.02), "busy": busy}, rounds=3,
                                 calls={"sleep": 4, "busy": 1})
    assert 0.005 <= samples["sleep"].median < 0.05
    assert samples["sleep"].cpu_median < 0.002
    assert samples["busy"].cpu_us >= 0.02e6
    # the two clocks tick apart: thread CPU may read a few microseconds above the wall clock
    assert samples["busy"].cpu_median <= 1.01 * samples["busy"].median


def test_from_rounds_gathers_wall_and_cpu_per_name():
    samples = timing.from_rounds([{"x": (3.0, 1.0)}, {"x": (1.0, 0.5)}, {"x": (2.0, 2.0)}])
    assert samples["x"].wall == (3.0, 1.0, 2.0) and samples["x"].cpu == (1.0, 0.5, 2.0)
    assert samples["x"].us == pytest.approx(2e6) and samples["x"].cpu_us == pytest.approx(1e6)
    assert timing.round_ratios(samples["x"], [1.5, 0.5, 4.0]) == [2.0, 2.0, 0.5]


def test_load_average_is_three_non_negative_figures():
    load = timing.load_average()
    assert len(load) == 3 and min(load) >= 0

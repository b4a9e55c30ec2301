"""Timing for every bench: functions called in interleaved rounds (so that they see the same machine
load), wall time and this thread's CPU time of each call, medians, minimum and maximum, the
per-round ratio of two timings (the spread of a comparison on a shared machine) and the machine's
load average to print beside them.

    samples = interleaved({"a": lambda i: step_a(), "b": lambda i: step_b()}, rounds=7, calls=1000)
    samples["a"].us           # median µs per call of a
    round_ratios(samples["a"], samples["b"])

A function is called with the round's index (a batch of a long record starts where that index
says); ``calls`` divides each round's time into a time per call (one count for all functions, or
one per function). Paths too unlike to share a round size (a batch of 100 steps, a whole run)
are timed each its own way within the same rounds and gathered by :func:`from_rounds`.
"""
from __future__ import annotations

import os
import statistics
import time
from dataclasses import dataclass
from typing import Callable, Mapping, Sequence


@dataclass(frozen=True)
class Samples:
    """Seconds per call of each round: ``wall`` (perf_counter) and ``cpu`` (this thread's CPU time,
    less sensitive to other jobs on the machine than wall time)."""
    wall: tuple[float, ...]
    cpu: tuple[float, ...]

    @property
    def median(self) -> float:
        return statistics.median(self.wall)

    @property
    def min(self) -> float:
        return min(self.wall)

    @property
    def max(self) -> float:
        return max(self.wall)

    @property
    def cpu_median(self) -> float:
        return statistics.median(self.cpu)

    @property
    def us(self) -> float:
        """Median µs per call."""
        return 1e6 * self.median

    @property
    def cpu_us(self) -> float:
        """Median µs of this thread's CPU time per call."""
        return 1e6 * self.cpu_median


def timed(function: Callable[[], object]) -> tuple[object, float, float]:
    """(what ``function`` returns, its wall seconds, this thread's CPU seconds) of one call."""
    start, cpu = time.perf_counter_ns(), time.thread_time_ns()
    result = function()
    return result, 1e-9 * (time.perf_counter_ns() - start), 1e-9 * (time.thread_time_ns() - cpu)


def interleaved(functions: Mapping[str, Callable[[int], object]], rounds: int,
                calls: int | Mapping[str, int] = 1) -> dict[str, Samples]:
    """Each function called once per round, in turn (round ``i`` calls every function with ``i``
    before round ``i + 1`` starts); the samples are seconds per call (a round's time / its
    ``calls``: one count, or a count per function)."""
    counts = calls if isinstance(calls, Mapping) else {name: calls for name in functions}
    wall = {name: [] for name in functions}
    cpu = {name: [] for name in functions}
    for i in range(max(1, rounds)):
        for name, function in functions.items():
            _, w, c = timed(lambda: function(i))
            wall[name].append(w / counts[name])
            cpu[name].append(c / counts[name])
    return {name: Samples(tuple(wall[name]), tuple(cpu[name])) for name in functions}


def from_rounds(rounds: Sequence[Mapping[str, tuple[float, float]]]) -> dict[str, Samples]:
    """The samples of each name from rounds of (wall, CPU) seconds per call, one mapping a round."""
    return {name: Samples(tuple(r[name][0] for r in rounds), tuple(r[name][1] for r in rounds)) for name in rounds[0]}


def load_average() -> tuple[float, float, float]:
    """The machine's load average over 1, 5 and 15 minutes (other jobs' demand for its cores)."""
    return tuple(round(v, 2) for v in os.getloadavg())


def repeated(function: Callable[[], object], rounds: int, calls: int = 1) -> Samples:
    """One function timed ``rounds`` times (:func:`interleaved` with nothing to alternate with)."""
    return interleaved({"f": lambda i: function()}, rounds, calls)["f"]


def round_ratios(numerator: Samples | Sequence[float], denominator: Samples | Sequence[float]) -> list[float]:
    """numerator / denominator of each round (wall time, or figures of one round each): timings
    taken under the same load."""
    def values(s):
        return s.wall if isinstance(s, Samples) else s
    return [a / b for a, b in zip(values(numerator), values(denominator))]


def medians(samples: Mapping[str, Samples]) -> dict[str, float]:
    """Median µs per call of each timing."""
    return {name: s.us for name, s in samples.items()}

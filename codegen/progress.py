"""What a cold build says while it works: which model, and C units compiled / units known.

A build that finds its library cached says nothing. A cold one (the first ``symkf build``, or
the build ``symkf compare`` and ``symkf.runtime.load`` start when the library is stale) writes to
stderr from its first second: ``symkf: building <model> ...``, then the units compiled against
the units generated so far (the total grows while the model's parts are still being generated;
it is final once generation ends), and a last line with the units compiled, those taken from the
object cache and the seconds. On a terminal the count is one line rewritten in place; elsewhere
(a log, a notebook's captured stderr) a line at most every ``LOG_EVERY_S`` seconds.
"""
from __future__ import annotations

import sys
import time

#: Seconds between two progress lines when stderr is not a terminal.
LOG_EVERY_S = 2.0


class BuildProgress:
    """Progress of one cold build on ``stream`` (default stderr)."""

    def __init__(self, model: str, stream=None):
        self.model, self.stream = model, stream or sys.stderr
        self.start = time.perf_counter()
        self.interactive = bool(getattr(self.stream, "isatty", lambda: False)())
        self._last_line = -LOG_EVERY_S
        self.done = self.total = 0
        self.final = False

    def begin(self) -> None:
        self._write(f"symkf: building {self.model} (generating C and compiling it; later loads use the cache)", True)

    def units(self, done: int, total: int, final: bool = False) -> None:
        """``done`` of the ``total`` compiles started so far have finished (``final``: no more to come)."""
        self.done, self.total, self.final = done, total, final or self.final
        elapsed = time.perf_counter() - self.start
        more = "" if self.final else " (still generating)"
        text = f"symkf: building {self.model}: {done}/{total} C units compiled{more}, {elapsed:.1f} s"
        if self.interactive:
            self.stream.write("\r" + text)
            self.stream.flush()
        elif elapsed - self._last_line >= LOG_EVERY_S or (self.final and done == total):
            self._write(text, True)
            self._last_line = elapsed

    def end(self, compiled: int, units: int) -> None:
        elapsed = time.perf_counter() - self.start
        cached = units - compiled
        if self.interactive:
            self.stream.write("\r")
        self._write(f"symkf: built {self.model} in {elapsed:.1f} s: {compiled} C units compiled"
                    + (f", {cached} from the object cache" if cached else ""), True)

    def _write(self, text: str, newline: bool) -> None:
        self.stream.write(text + ("\n" if newline else ""))
        self.stream.flush()

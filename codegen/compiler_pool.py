"""Compiler commands run in the background, each in a process group that dies with this process.

A killed build leaves no compiler behind: each command runs under a guard shell that kills its
whole process group (cc and its cc1, as, ld) on SIGTERM, which the kernel sends when the building
process dies (PR_SET_PDEATHSIG, set by util-linux's setpriv or in the child).
"""
from __future__ import annotations

import ctypes
import functools
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path


#: The compiler runs under a shell that kills its whole process group (cc and its cc1, as, ld)
#: when it receives SIGTERM, which the kernel sends when the building process dies (any signal).
_GROUP_GUARD = ["/bin/sh", "-c", 'trap "kill -KILL 0" TERM; "$@" & wait $!', "symkf-cc"]


def _term_with_parent() -> None:
    """In the child: SIGTERM when the parent dies (Linux PR_SET_PDEATHSIG; kept across exec)."""
    try:
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)
    except (AttributeError, OSError):
        pass


@functools.lru_cache(maxsize=1)
def _pdeathsig_wrapper() -> tuple[str, ...]:
    """``setpriv --pdeathsig TERM --`` if util-linux's setpriv has that option (2.33+), else ().
    It sets what :func:`_term_with_parent` sets, from a program of its own: without a Python
    ``preexec_fn`` the compiler is started by vfork, not by a fork of this (large) process,
    about 2 ms instead of 10-20 per unit on the build's serial path."""
    setpriv = shutil.which("setpriv")
    if setpriv is None:
        return ()
    try:
        ok = subprocess.run([setpriv, "--pdeathsig", "TERM", "--", "true"], capture_output=True, timeout=10).returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        ok = False
    return (setpriv, "--pdeathsig", "TERM", "--") if ok else ()


def _spawn(cmd: list[str], cwd: Path, stderr) -> subprocess.Popen:
    """The command in its own session and process group, under the guard shell that kills the
    group when this process dies (SIGTERM from PR_SET_PDEATHSIG, set by setpriv or in the child)."""
    linux = sys.platform.startswith("linux")
    wrapper = list(_pdeathsig_wrapper()) if linux else []
    return subprocess.Popen(wrapper + (_GROUP_GUARD if linux else []) + cmd, cwd=cwd, stdout=subprocess.DEVNULL,
                            stderr=stderr, start_new_session=True,
                            preexec_fn=_term_with_parent if linux and not wrapper else None)


def run_compiler(cmd: list[str], cwd: Path) -> tuple[int, str]:
    """Run one compiler command (see :func:`run_compilers`)."""
    return run_compilers([cmd], cwd)[0]


def run_compilers(cmds: list[list[str]], cwd: Path, jobs: int | None = None) -> list[tuple[int, str]]:
    """Run compiler commands, ``jobs`` at a time (default: one per core), each in its own process
    group that dies with this process; on any exception here (Ctrl-C) every group is killed.
    Returns (return code, stderr) per command."""
    with CompilerPool(cwd, jobs) as pool:
        indices = [pool.submit(cmd) for cmd in cmds]
        results = pool.wait()
    return [results[i] for i in indices]


class CompilerPool:
    """Compiler commands run ``jobs`` at a time (default: one per core) in the background while
    this process goes on: each in its own process group that dies with this process, started when
    submitted or at the next :meth:`poll` (a builder polls between its steps); leaving the ``with``
    block on an exception (Ctrl-C) kills every group still running. Queued commands start highest
    priority first, and one of higher priority than every running command starts at once if a
    core is left (``cores``, default: all): the longest compile never waits behind a shorter one."""

    def __init__(self, cwd: Path, jobs: int | None = None, cores: int | None = None, on_finished=None):
        self.cwd, self.jobs = cwd, max(1, jobs or os.cpu_count() or 1)
        #: called as ``on_finished(finished, submitted)`` when commands finish (cancelled ones, and
        #: those submitted with ``counted=False``, not counted)
        self.on_finished = on_finished
        self.cancelled: set[int] = set()
        self.uncounted: set[int] = set()
        self.cores = max(self.jobs, cores or os.cpu_count() or 1)
        self.pending: list[tuple[int, list[str]]] = []
        self.running: dict[int, tuple[subprocess.Popen, object]] = {}
        self.results: dict[int, tuple[int, str]] = {}
        self.priority: dict[int, float] = {}
        self.submitted = 0

    def __enter__(self) -> "CompilerPool":
        return self

    def __exit__(self, kind, value, traceback) -> None:
        if kind is not None:
            for index in list(self.running):
                self.cancel(index)

    def submit(self, cmd: list[str], priority: float = 0, counted: bool = True) -> int:
        """Queue a command (started at once if a slot is free; queued ones start highest
        ``priority`` first, in order of submission among equals); returns its index. A command
        not ``counted`` is left out of ``on_finished``'s figures (a unit's second compile)."""
        if not counted:
            self.uncounted.add(self.submitted)
        self.pending.append((self.submitted, cmd))
        self.priority[self.submitted] = priority
        self.pending.sort(key=lambda item: -self.priority[item[0]])
        self.submitted += 1
        self.poll()
        return self.submitted - 1

    def poll(self) -> None:
        """Collect finished commands and start queued ones in the free slots."""
        finished = False
        for index, (proc, log) in list(self.running.items()):
            if proc.poll() is not None:
                log.seek(0)
                self.results[index] = (proc.returncode, log.read())
                log.close()
                del self.running[index]
                finished = True
        if finished and self.on_finished is not None:
            left_out = self.cancelled | self.uncounted
            self.on_finished(sum(1 for index in self.results if index not in left_out), self.submitted - len(left_out))
        while self.pending and (len(self.running) < self.jobs or self._outranks_running()):
            index, cmd = self.pending.pop(0)
            log = tempfile.TemporaryFile(mode="w+")
            self.running[index] = (_spawn(cmd, self.cwd, log), log)

    def _outranks_running(self) -> bool:
        """The next queued command has a higher priority than every running one, and a core is free."""
        first = self.priority[self.pending[0][0]]
        return len(self.running) < self.cores and all(first > self.priority[index] for index in self.running)

    def cancel(self, index: int) -> None:
        """Drop a queued command, or kill a running one (its process group) and wait for it."""
        self.pending = [item for item in self.pending if item[0] != index]
        if index in self.running:
            proc, log = self.running.pop(index)
            try:
                os.killpg(proc.pid, signal.SIGKILL)
            except OSError:
                pass
            proc.wait()
            log.close()
        if index not in self.results:
            self.cancelled.add(index)
        self.results[index] = (-signal.SIGKILL, "cancelled")

    def wait(self) -> dict[int, tuple[int, str]]:
        """Wait for every submitted command; (return code, stderr) by index."""
        self.poll()
        while self.pending or self.running:
            time.sleep(0.005)
            self.poll()
        return self.results


"""The C fast path of :meth:`Filter.step <symkf.runtime.filters.Filter.step>` and its trusted-step
replay, the machinery a :class:`~symkf.runtime.filters.Filter` owns beside its state API.

:class:`FastPath` makes, per measurement, the C ``Step`` of :mod:`symkf.runtime.fastcall` (the
contract's checks, the copies and the kernel call in one C call) and installs the C ``Method``
over ``Filter.step`` on the filter, so a plain call runs no Python frame.

Where a step kernel has a trusted partner (the kernel its C run loop iterates once a step has
succeeded, ``Kernel.trusted``: an MEKF's step without the checks of |q| = 1, P PSD and R diagonal
and without y, S), the Step calls that partner while x and P are the filter's own (a step
succeeded and nothing was written from Python since: :attr:`FastPath.own_state`): the same x, P
and codes. It keeps the step's inputs (a :class:`Replay`), and the filter's ``y`` / ``S`` compute
the diagnostics from them when asked, with the checked step kernel: bit-identical to a checked
step's. Every write from Python first calls :meth:`FastPath.before_write`: that replay, and the
next step a checked one.
"""
from __future__ import annotations

from copy import deepcopy
from dataclasses import dataclass

import numpy as np

from symkf.codegen.spec import STATUS_GATED
from . import fastcall
from .contract import read_only


#: The array arguments of ``Filter.step`` in the order its fast path takes them.
ARGUMENTS = ("z", "q", "mask", "u")
#: What the fast path writes for an omitted (None) array: a mask is all ones; any other argument
#: with values (z, q, an input ``u``) is required: the Python path says so, or holds ``u="hold"``.
IF_NONE = {"mask": "ones"}
#: How the fast path checks an array: a mask is exactly 0 or 1; z must be finite where the
#: mask uses it (the kernel never reads a masked component; the Python path accepts a NaN
#: there too); anything else finite.
CHECK = {"mask": "mask", "z": "used"}


@dataclass
class Replay:
    """What a trusted step (module docstring) of one measurement needs and leaves: the trusted
    kernel's name, that step's carried state and per-step inputs, kept by the C fast path, and
    whether its y, S are still to be computed from them (``stale[0]`` = 1, set in C)."""

    kernel: str
    buffers: dict[str, np.ndarray]
    stale: np.ndarray


def trusted_kernel(backend, spec, name: str) -> str:
    """The trusted partner of the run kernel of measurement ``name`` if it takes the step
    kernel's inputs and writes some of its outputs (x, P, status), else ""."""
    kernels = backend.kernels
    step = kernels[spec.step[name]]
    run = kernels.get(spec.run.get(name, ""))
    trusted = kernels.get(run.trusted) if run is not None and run.trusted else None
    fits = trusted is not None and trusted.inputs == step.inputs and set(trusted.outputs) <= set(step.outputs)
    return trusted.name if fits else ""


class FastPath:
    """A filter's fast steps and trusted-step replays (module docstring).

    The data (the :class:`Replay` per measurement with a trusted kernel and the ``own_state``
    flag the C step sets once a step has succeeded, 0 after any write from Python) is made with
    the filter's buffers and copied with it; the calls are bound by :meth:`bind`, after the
    filter's own kernel calls, and bound afresh for a copy.
    """

    def __init__(self, filt):
        self.own_state = np.zeros(1)
        self.replays: dict[str, Replay] = {}
        for name, kernel in filt.spec.step.items():
            trusted = trusted_kernel(filt._backend, filt.spec, name)
            if trusted:
                live = filt._measurement_buffers(name)
                kept = [n for n in filt.spec.state + filt.kernels[kernel].per_step if live[n].size]
                self.replays[name] = Replay(trusted, {n: live[n].copy(order="K") for n in kept}, np.zeros(1))
        self.steps: dict = {}
        self.default = None

    def copy(self) -> "FastPath":
        """The data of this fast path (replays, own_state), unbound: a copy's filter binds it."""
        clone = object.__new__(FastPath)
        clone.own_state, clone.replays = self.own_state.copy(), deepcopy(self.replays)
        clone.steps, clone.default = {}, None
        return clone

    def bind(self, filt, function) -> None:
        """Bind the trusted and replay calls over ``filt``'s buffers, then the fast steps
        (:meth:`switch_on`); ``function`` is ``Filter.step``."""
        self._filter, self._function = filt, function
        self.trusted_calls, self.replay_calls = {}, {}
        self.measurements, self.diagnostics = filt.measurements, filt.spec.diagnostics
        self.views = {}
        for name, replay in self.replays.items():
            live = filt._measurement_buffers(name)
            # its inputs are tested by the fast path (arguments), by the setters (constants) and on
            # output (x, P): the entry without the inputs' finiteness test (0.6k instructions for the MEKF)
            self.trusted_calls[name] = filt._backend.bind(replay.kernel, live, entry="unchecked_v")
            self.replay_calls[name] = filt._backend.bind(filt.spec.step[name], {**live, **replay.buffers})
        self.switch_on()

    def switch_on(self) -> None:
        """The C fast step per measurement (None without the extension), and the filter's ``step``
        taking plain calls in C."""
        filt = self._filter
        self.steps = {name: self._step(name) for name in filt.spec.step}
        self.default = self.steps.get(filt._default)
        self._install(self.default, ("t", "dt") + ARGUMENTS)

    def switch_off(self) -> None:
        """Every call of ``step`` through the Python contract."""
        self.steps, self.default = {}, None
        self._filter.__dict__.pop("step", None)

    @property
    def calls(self) -> int:
        """How many calls of ``step`` took the C fast path (since it was last switched on)."""
        return sum(step.calls for step in self.steps.values() if step is not None)

    def _install(self, default, arguments: tuple) -> None:
        """Set the filter's ``step`` to a C :func:`~symkf.runtime.fastcall.method` over
        ``Filter.step``: a plain call then runs no Python frame (that frame was ~1,000 of the ~2,200
        instructions a call cost beyond the kernel); any other call runs ``Filter.step``. Only
        where the filter's class keeps ``Filter.step`` (a subclass's own ``step`` is left alone)."""
        filt = self._filter
        filt.__dict__.pop("step", None)
        if type(filt).step is self._function:
            fast = fastcall.method(self._function, filt, default, arguments, steps=self.steps, select="measurement")
            if fast is not None:
                filt.step = fast

    def _step(self, name: str):
        """The fast path of ``step`` with measurement ``name`` (None without the C extension)."""
        filt = self._filter
        buffers, shared = filt.measurements[name], filt._buffers
        slots = []
        for key in ARGUMENTS:
            buffer = buffers.get(key, shared.get(key) if key == "u" else None)
            if buffer is None:
                slots.append((None, "absent", "finite"))
            else:
                required = "decline" if buffer.size else "keep"
                slots.append((buffer, IF_NONE.get(key, required), CHECK.get(key, "finite")))
        trusted = None
        if name in self.replays:
            replay, live = self.replays[name], filt._measurement_buffers(name)
            trusted = (self.trusted_calls[name], self.own_state, replay.stale,
                       [(live[n], kept, n in filt.spec.state) for n, kept in replay.buffers.items()])
        return fastcall.step(filt._calls[filt.spec.step[name]], shared.get("t"), shared.get("dt"),
                             filt._clock, slots, (shared, buffers), trusted)

    def before_write(self) -> None:
        """Before anything is written from Python: the diagnostics trusted steps left (they read
        those steps' inputs and the constants about to change), and the next fast step is a
        checked one (the trusted kernel relies on a state only steps wrote)."""
        for name in self.replays:
            self.replay(name)
        self.own_state[0] = 0.0

    def replay(self, name: str) -> None:
        """y, S of the last step with measurement ``name`` if a trusted step left them: the checked
        step kernel on the inputs it kept (the same expressions: a checked step's y, S bit for bit;
        its x, P land in the replay's buffers). NaN if that kernel refuses what the trusted one
        took: a P off the PSD test after a successful step (none seen; codegen/families/mekf.py
        ``mekf_run_kernels``)."""
        replay = self.replays.get(name)
        if replay is None or not replay.stale[0]:
            return
        replay.stale[0] = 0.0
        if self.replay_calls[name]() not in (0, STATUS_GATED):
            for key in self.diagnostics:
                self.measurements[name][key][...] = np.nan

    def diagnostic(self, key: str, name: str):
        """The read-only view of diagnostic ``key`` of measurement ``name`` (made once), replayed
        first if a trusted step left it."""
        self.replay(name)
        if (name, key) not in self.views:
            self.views[name, key] = read_only(self.measurements[name][key])
        return self.views[name, key]

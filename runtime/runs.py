"""Whole runs of a :class:`~symkf.runtime.filters.Filter`: the per-step arrays of a record,
checked by the rules of one step (:mod:`symkf.runtime.contract`) for every row at once, the run
loop (the generated C ``<kernel>_run`` or, on the CasADi-VM backend, the same kernel step by
step) and its :class:`RunResult`."""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np

from symkf.codegen.spec import STATUS_CODES, STATUS_GATED
from . import calls, contract, innovations, precision
from .backends import SymkfError
from .buffers import buffer, fits

#: What a run does when a step is refused (a SYMKF_ERR_* code: the state kept, time advanced):
#: "raise" (the default: :class:`RunRefused`, the filter as before the run) or "continue".
REFUSED_POLICIES = ("raise", "continue")


@dataclass
class RunResult(innovations.Innovations):
    """A whole run: the state (and covariance) after every step and each step's status code.
    ``refused_steps`` / ``counts`` say which steps failed and how; ``repr`` shows them."""

    x: np.ndarray                  # (N, n)
    P: np.ndarray | None           # (N, n, n), None for a filter without covariance
    status: np.ndarray             # (N,) int: 0, SYMKF_GATED or a SYMKF_ERR_* code
    #: The run's per-step t, dt (and u) and the constants its kernel read, by argument name, as the
    #: kernels take them: what a smoother needs (runtime/smoothing.py).
    inputs: dict = field(default_factory=dict, repr=False)
    #: The run loop's y and S histories and the run's mask, as kept (read through the properties
    #: y, S, nis, nis_dof of :class:`~symkf.runtime.innovations.Innovations`).
    innovations: dict = field(default_factory=dict, repr=False)

    def __repr__(self) -> str:
        shape = f"{self.x.shape[0]} steps x {self.x.shape[1]} states"
        counts = ", ".join(f"{name}: {count}" for name, count in self.counts.items()) or "all OK"
        refused = self.refused_steps
        where = f"; refused steps {refused[:10].tolist()}{' ...' if refused.size > 10 else ''}" if refused.size else ""
        return f"RunResult({shape}; {counts}{where})"

    @property
    def counts(self) -> dict[str, int]:
        """Steps per status other than OK, by name (e.g. {"SYMKF_GATED": 2, "SYMKF_ERR_NOT_PD": 1})."""
        codes, counts = np.unique(self.status[self.status != 0], return_counts=True)
        return {STATUS_CODES.get(int(c), (f"code {int(c)}",))[0]: int(n) for c, n in zip(codes, counts)}

    @property
    def refused_steps(self) -> np.ndarray:
        """Steps that failed (state kept, time advanced); gated steps are not failures."""
        return np.flatnonzero((self.status != 0) & (self.status != STATUS_GATED))

    @property
    def failed_steps(self) -> np.ndarray:
        """The same as :attr:`refused_steps`."""
        return self.refused_steps

    def refused_codes(self) -> np.ndarray:
        """The SYMKF_ERR_* code of each refused step."""
        return self.status[self.refused_steps]

    @property
    def gated_steps(self) -> int:
        """Number of steps whose update the chi-square gate refused."""
        return int(np.count_nonzero(self.status == STATUS_GATED))

    @property
    def q(self) -> np.ndarray:
        """The attitude quaternions (first four states) of an attitude or MARG filter."""
        return self.x[:, 0:4]


def series(filt, name: str, n_steps: int, given: dict, u, nan: str) -> dict[str, np.ndarray]:
    """Validated per-step arrays of a run of ``filt`` (same rules as step(), for every row at once)."""
    nan = contract.nan_policy(nan)
    buffers = filt.measurements[name]
    result = {}
    for key, value in given.items():
        if key not in buffers:
            if value is not None:
                raise ValueError(f"{key}: measurement '{name}' of filter '{filt.family}' takes no {key}")
            continue
        shape = buffers[key].shape
        if key == "q" and value is None and buffers[key].size:
            params = [v["name"] for v in filt.model["measurements"][name]["params"]]
            raise ValueError(f"q: measurement '{name}' needs its parameters {params} (q=...)")
        if key == "mask":
            result[key] = np.ones((n_steps,) + shape) if value is None else contract.mask(value, (n_steps,) + shape)
        elif value is None and not buffers[key].size:
            result[key] = np.zeros((n_steps,) + shape)
        else:
            result[key] = _held(key, value, n_steps, shape)
    shared = filt._buffers
    if "u" in shared:
        held = u is None or (isinstance(u, str) and u == calls.HOLD)
        if held:
            calls.u_input(filt, u, "run")           # a model with inputs: None is an error, "hold" is said
        result["u"] = _held("u", shared["u"] if held else u, n_steps, shared["u"].shape)
        if not np.isfinite(result["u"]).all():
            raise ValueError("u: contains NaN or Inf")
    elif u is not None:
        raise ValueError(f"u: model '{filt.model['name']}' has no inputs")
    return _nan_policy(result, nan)


def _held(key: str, value, n_steps: int, shape: tuple) -> np.ndarray:
    if np.shape(value) == shape:                          # one value held for every step
        return np.broadcast_to(contract.as_array(key, value, shape), (n_steps,) + shape)
    return contract.as_array(key, value, (n_steps,) + shape)


def _nan_policy(result: dict, nan: str) -> dict:
    """NaN policy and finiteness for a run: every used component must be finite ("raise"),
    or non-finite components are masked ("mask"); masked components are zeroed."""
    if "z" not in result:
        return result
    z, mask = result["z"], result["mask"]
    finite = np.isfinite(z)
    per_component = mask.shape == z.shape
    used = mask > 0.5 if per_component else np.broadcast_to(mask > 0.5, z.shape)
    if nan == "mask":
        mask = mask * (finite if per_component else finite.all(axis=1, keepdims=True))
    elif np.any(used & ~finite):
        rows = np.flatnonzero(np.any(used & ~finite, axis=1))
        raise ValueError(f"z: NaN/Inf in used components at steps {rows[:10].tolist()}; pass nan='mask' to skip them")
    for key, value in result.items():
        if key not in ("z", "mask") and not np.isfinite(value).all():
            raise ValueError(f"{key}: contains NaN or Inf")
    result["mask"] = mask
    keep = mask > 0.5 if per_component else np.broadcast_to(mask > 0.5, z.shape)
    result["z"] = np.where(keep, z, 0.0)
    return result


class RunRefused(SymkfError):
    """A run in which steps were refused (a SYMKF_ERR_* code each: that step kept the state while
    time advanced). The filter is as it was before the run; ``result`` is the whole run's
    :class:`RunResult`, ``steps`` the refused indices, ``codes`` their codes."""

    def __init__(self, what: str, result: RunResult):
        self.result, self.steps = result, result.refused_steps
        self.codes = result.refused_codes()
        first = int(self.steps[0])
        counts = ", ".join(f"{n}: {c}" for n, c in result.counts.items() if n != "SYMKF_GATED")
        detail = (f"{self.steps.size} of {result.status.size} steps refused ({counts}), the first at step {first}; "
                  "the filter is as before the run, the run's result is this error's .result; pass "
                  "refused='continue' to run past refused steps")
        super().__init__(what, int(self.codes[0]), detail)


#: A run's first step (from the filter's time to times[0]) this many times longer than the record's
#: median step is said: most often x0 belongs to times[0] and the filter was made without t0.
LONG_FIRST_STEP = 10.0


def steps_from_clock(filt, times: np.ndarray, call: str) -> dict[str, np.ndarray]:
    """The per-step t and dt of a record of ``times`` (checked by ``contract.run_times``) on the
    filter's clock: step 0 from the filter's time to times[0] (dt = 0, an update first, when
    times[0] is that time; a time before it is refused), then from each time to the next."""
    start = filt.t
    if times.size and (times[0] < start or contract.is_on_clock(times[0], start)):
        start = contract.on_clock(times[0], start, 0.0, f"{call} (its first time)")
    per_step = {"t": np.concatenate([[start], times[:-1]]), "dt": np.diff(times, prepend=start)}
    warn_long_first_step(filt, times, per_step["dt"])
    return per_step


def warn_long_first_step(filt, times: np.ndarray, dt: np.ndarray) -> None:
    if times.size > 1 and dt[0] > LONG_FIRST_STEP * float(np.median(np.diff(times))):
        warnings.warn(f"run: the first step propagates {dt[0]:.6g} s, from the filter's time {filt.t!r} to times[0] = "
                      f"{times[0]!r} (the record's steps are {float(np.median(np.diff(times))):.3g} s); if x0 is the "
                      f"state at {times[0]!r}, make the filter with t0={times[0]!r} or set filter.t first",
                      RuntimeWarning, stacklevel=3)


def run(filt, name: str, per_step: dict, given: dict, u, nan: str, refused: str = "raise") -> RunResult:
    """A run of ``filt`` with measurement ``name``: ``per_step`` t and dt, the measurement's
    ``given`` arrays and ``u`` checked (:func:`series`), then the run loop, written once: the C
    ``<kernel>_run`` or, on the VM backend, step by step (the filter's run kernel,
    ``FilterSpec.run``, else its step kernel). Its x, P and t end at the last step, unless a step
    was refused and ``refused`` is "raise" (:class:`RunRefused`; x, P, t as before)."""
    if refused not in REFUSED_POLICIES:
        raise ValueError(f"refused: expected one of {REFUSED_POLICIES}, got {refused!r}")
    n_steps = per_step["dt"].size
    per_step.update(series(filt, name, n_steps, given, u, nan))
    kernel = filt.spec.run.get(name, filt.spec.step[name])
    histories, status, kept, arrays = _loop(filt, kernel, name, per_step, n_steps)
    result = _result(filt, histories, status)
    info = filt._backend.kernels[kernel]
    result.inputs = {n: a.copy() for (n, _), a in zip(info.inputs, arrays)
                     if n not in filt.spec.state and (n in ("t", "dt", "u") or n not in info.per_step)}
    result.innovations = {"kept": kept, "mask": per_step.get("mask")}
    if result.gated_steps and name in filt._default_gates:
        warnings.warn(f"{filt.family} run '{name}': {result.gated_steps} of {n_steps} updates refused by the default "
                      f"innovation gate (chi-square probability {contract.DEFAULT_GATE_PROBABILITY!r}); set "
                      f"gate={{'{name}': None}} to fuse every update, or a probability of your own", RuntimeWarning,
                      stacklevel=3)
    if refused == "raise" and result.refused_steps.size:
        raise RunRefused(f"{filt.family} run '{name}'", result)
    if n_steps:
        for n in filt.spec.state:
            filt._buffers[n][...] = histories[n][-1].T
        if "u" in per_step and filt._buffers["u"].size:
            filt._buffers["u"][:] = per_step["u"][-1]     # the input a later u="hold" keeps
            filt._u_given = True
        filt.t = float(per_step["t"][-1] + per_step["dt"][-1]) if "t" in per_step else \
            filt.t + float(np.sum(per_step["dt"]))
    return result


def _loop(filt, kernel: str, name: str, per_step: dict, n_steps: int):
    """The run loop over checked per-step arrays: histories of the carried state, the status, the
    diagnostics y, S the loop kept (a filter that has them) and the kernel's input arrays."""
    info = filt._backend.kernels[kernel]
    constants = filt._measurement_buffers(name)
    dtype = filt._dtype
    for n in info.per_step:
        fits(filt._dtype, n, per_step[n])
    arrays = [np.ascontiguousarray(per_step[n], dtype=dtype) if n in info.per_step
              else np.asfortranarray(constants[n], dtype=dtype) for n, _ in info.inputs]
    histories = {n: np.zeros((n_steps,) + filt._buffers[n].shape[::-1], dtype) for n in filt.spec.state}
    kept = {n: np.zeros((n_steps,) + buffer(shape).shape[::-1], dtype) for n, shape in info.outputs if n in info.diagnosed}
    status = np.zeros(n_steps, dtype=np.intc)
    filt._fast.before_write()
    loop = filt._backend.run_function(kernel, diagnostics=bool(kept))
    if loop is not None:
        loop(n_steps, *[a.ctypes.data for a in arrays], *[histories[n].ctypes.data for n in filt.spec.state],
             *[a.ctypes.data for a in kept.values()], status.ctypes.data)
    else:
        _run_in_python(filt, kernel, info, arrays, {**histories, **kept}, status)
    return histories, status, kept, arrays


def _result(filt, histories: dict, status: np.ndarray) -> RunResult:
    x = histories["x"]
    P = np.transpose(histories["P"], (0, 2, 1)) if "P" in histories else None
    precision.warn_unresolved(filt, x, P)                 # a float build: says which state float cannot hold
    if P is not None and filt._form is not None:          # a square-root filter's factors
        P = filt._form.from_kernel(P)
    if filt._scaling is not None:
        x, P = filt._scaling.x_from_kernel(x), None if P is None else filt._scaling.P_from_kernel(P)
    return RunResult(np.asarray(x, dtype=float), None if P is None else np.asarray(P, dtype=float), status)


def _run_in_python(filt, kernel, info, arrays, histories, status) -> None:
    """The run loop for the VM backend: the same kernel, step by step, on scratch buffers."""
    buffers = {n: buffer(shape, filt._dtype) for n, shape in info.inputs + info.outputs[:-1]}
    for (n, _), array in zip(info.inputs, arrays):
        if n not in info.per_step:
            buffers[n].reshape(-1, order="F")[:] = array.reshape(-1, order="F")
    call = filt._backend.bind(kernel, buffers)
    for k in range(status.size):
        for (n, _), array in zip(info.inputs, arrays):
            if n in info.per_step:
                buffers[n].reshape(-1, order="F")[:] = array[k].reshape(-1)
        status[k] = call()
        for n, history in histories.items():
            history[k] = buffers[n].T

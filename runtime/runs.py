"""Whole runs of a :class:`~symkf.runtime.filters.Filter`: the per-step arrays of a record,
checked by the rules of one step (:mod:`symkf.runtime.contract`) for every row at once, the run
loop (the generated C ``<kernel>_run`` or, on the CasADi-VM backend, the same kernel step by
step) and its :class:`RunResult`."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from symkf.codegen.spec import STATUS_GATED
from . import contract, innovations
from .buffers import buffer, fits


@dataclass
class RunResult(innovations.Innovations):
    """A whole run: the state (and covariance) after every step and each step's status code."""

    x: np.ndarray                  # (N, n)
    P: np.ndarray | None           # (N, n, n), None for a filter without covariance
    status: np.ndarray             # (N,) int: 0, SYMKF_GATED or a SYMKF_ERR_* code
    #: The run's per-step t, dt (and u) and the constants its kernel read, by argument name, as the
    #: kernels take them: what a smoother needs (runtime/smoothing.py).
    inputs: dict = field(default_factory=dict, repr=False)
    #: The run loop's y and S histories and the run's mask, as kept (read through the properties
    #: y, S, nis, nis_dof of :class:`~symkf.runtime.innovations.Innovations`).
    innovations: dict = field(default_factory=dict, repr=False)

    @property
    def failed_steps(self) -> np.ndarray:
        """Steps that failed (state kept); gated steps are not failures."""
        return np.flatnonzero((self.status != 0) & (self.status != STATUS_GATED))

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
        result["u"] = _held("u", shared["u"] if u is None else u, n_steps, shared["u"].shape)
        if not np.isfinite(result["u"]).all():
            raise ValueError("u: contains NaN or Inf")
    elif u is not None:
        raise ValueError(f"u: filter '{filt.family}' has no inputs")
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


def run(filt, name: str, per_step: dict, given: dict, u, nan: str) -> RunResult:
    """A run of ``filt`` with measurement ``name``: ``per_step`` t and dt, the measurement's
    ``given`` arrays and ``u`` checked (:func:`series`), then the run loop, written once: the C
    ``<kernel>_run`` or, on the VM backend, step by step (the filter's run kernel,
    ``FilterSpec.run``, else its step kernel). Its x, P and t end at the last step."""
    n_steps = per_step["dt"].size
    per_step.update(series(filt, name, n_steps, given, u, nan))
    kernel = filt.spec.run.get(name, filt.spec.step[name])
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
    if n_steps:
        for n in filt.spec.state:
            filt._buffers[n][...] = histories[n][-1].T
        filt.t = float(per_step["t"][-1] + per_step["dt"][-1]) if "t" in per_step else \
            filt.t + float(np.sum(per_step["dt"]))
    x = histories["x"]
    P = np.transpose(histories["P"], (0, 2, 1)) if "P" in histories else None
    if filt._scaling is not None:
        x, P = filt._scaling.x_from_kernel(x), None if P is None else filt._scaling.P_from_kernel(P)
    inputs = {n: a.copy() for (n, _), a in zip(info.inputs, arrays)
              if n not in filt.spec.state and (n in ("t", "dt", "u") or n not in info.per_step)}
    return RunResult(np.asarray(x, dtype=float), None if P is None else np.asarray(P, dtype=float), status, inputs,
                     {"kept": kept, "mask": per_step.get("mask")})


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

"""Monte Carlo runs of one filter over one clock, stepped in lockstep: :meth:`Filter.run_lockstep`.

    results = f.run_lockstep(times, z_runs, "radar", q=stations)      # z_runs: (runs, N, m)

Every run starts from the filter's x, P and t (the filter is left as it is) and sees the same
times, u and q; each has its own z (and mask, if given per run). The result is one
:class:`~symkf.runtime.runs.RunResult` per run, equal bit for bit to what :meth:`Filter.run` returns
for that run from the same state: the generated ``<kernel>_run_lockstep`` steps 4 runs per AVX2
vector and hands every step the scalar code would not have taken cleanly to the scalar step
(codegen/c_backend/lockstep.py). A library built with ``<family>_lockstep_vector_math`` (the
launcher campaign's) calls libmvec in the prediction's lanes: each run then differs from
:meth:`Filter.run` by libmvec's round-off, its codes and refused steps the same. Without that loop (the CasADi-VM backend, a CPU without AVX2, a
family or build that has none) each run is :meth:`Filter.run` in turn: the same numbers, slower.
"""
from __future__ import annotations

import ctypes
import warnings

import numpy as np

from symkf.codegen.spec import STATUS_ARGS
from . import calls, contract, runs
from .buffers import buffer, fits


def run_lockstep(filt, times, z, measurement: str | None = None, q=None, mask=None, u=None,
                 nan: str = "raise", refused: str = "raise") -> list:
    """The runs of ``filt`` over ``times``, one per z[r] (see the module docstring). ``mask``: None,
    (N, m) shared or (runs, N, m); ``refused``: "raise" (:class:`~symkf.runtime.runs.RunRefused`
    of the first run with a refused step) or "continue"."""
    if refused not in runs.REFUSED_POLICIES:
        raise ValueError(f"refused: expected one of {runs.REFUSED_POLICIES}, got {refused!r}")
    name = calls.measurement_name(filt, measurement, "step", "run_lockstep")
    times = contract.run_times(times)
    z = np.asarray(z, dtype=float)
    if z.ndim != 3 or z.shape[1] != times.size:
        raise ValueError(f"z: expected (runs, {times.size}, m) for {times.size} times, got shape {z.shape}")
    masks = _masks(mask, z.shape)
    per_step = runs.steps_from_clock(filt, times, "run_lockstep")
    given = [{"z": z[r], "q": q, "mask": masks[r]} for r in range(z.shape[0])]
    loop = _lockstep_loop(filt, name)
    results = None
    if loop is not None and given:
        results = loop(per_step, [_checked(filt, name, times.size, g, u, nan, r) for r, g in enumerate(given)])
    if results is None:                        # no lockstep loop here (or it declined: no AVX2 at run time)
        return _one_by_one(filt, name, per_step, given, u, nan, refused)
    _warn_default_gate(filt, name, results)
    if refused == "raise":
        for r, result in enumerate(results):
            if result.refused_steps.size:
                raise runs.RunRefused(f"{filt.family} run_lockstep '{name}' (run {r})", result)
    return results


def _checked(filt, name: str, n_steps: int, given: dict, u, nan: str, run: int) -> dict:
    """Run ``run``'s arrays checked by the rules of one run; an error names the run."""
    try:
        return runs.series(filt, name, n_steps, given, u, nan)
    except ValueError as exc:
        raise ValueError(f"run {run}: {exc}") from None


def _masks(mask, shape: tuple) -> list:
    """One mask per run: None (all used), a shared (N, m) or per-run (runs, N, m) array."""
    if mask is None or np.ndim(mask) < 3:
        return [mask] * shape[0]
    if np.shape(mask)[0] != shape[0]:
        raise ValueError(f"mask: {np.shape(mask)[0]} runs, z has {shape[0]}")
    return list(mask)


def _one_by_one(filt, name: str, per_step: dict, given: list, u, nan: str, refused: str) -> list:
    """Each run through :func:`runs.run` from the filter's state, which is then put back."""
    state = {n: filt._buffers[n].copy() for n in filt.spec.state}
    t, results = filt.t, []
    try:
        for arrays in given:
            for n in filt.spec.state:
                filt._buffers[n][...] = state[n]
            filt.t = t
            results.append(runs.run(filt, name, dict(per_step), arrays, u, nan, refused))
    finally:
        for n in filt.spec.state:
            filt._buffers[n][...] = state[n]
        filt.t = t
    return results


def _lockstep_loop(filt, name: str):
    """The compiled lockstep loop of the filter's step with ``name``, or None."""
    backend = filt._backend
    if backend.kind != "compiled" or filt._scaling is not None or filt._form is not None or filt._dtype != np.float64:
        return None
    kernel = filt.spec.run.get(name, filt.spec.step[name])
    function = backend.lockstep_function(kernel)
    if function is None:
        return None
    info = backend.kernels[kernel]
    function.argtypes = [ctypes.c_int, ctypes.c_int] + [ctypes.c_void_p] * (len(info.inputs) + 5)
    function.restype = ctypes.c_int

    def loop(per_step: dict, checked: list):
        n_runs, n_steps = len(checked), per_step["dt"].size
        arrays = _inputs(filt, info, name, per_step, checked)
        shapes = {n: filt._buffers[n].shape[::-1] for n in ("x", "P")}
        kept_shapes = {n: buffer(shape).shape[::-1] for n, shape in info.outputs if n in ("y", "S")}
        hist = {n: np.zeros((n_runs, n_steps) + shapes[n]) for n in ("x", "P")}
        kept = {n: np.zeros((n_runs, n_steps) + kept_shapes[n]) for n in ("y", "S")}
        status = np.zeros((n_runs, n_steps), np.intc)
        filt._fast.before_write()
        code = function(n_runs, n_steps, *[a.ctypes.data for a in arrays],
                        *[hist[n].ctypes.data for n in ("x", "P")], *[kept[n].ctypes.data for n in ("y", "S")],
                        status.ctypes.data)
        if code == STATUS_ARGS and not status.any():
            return None
        return [_result(filt, info, arrays, per_step, checked[r], {n: hist[n][r] for n in hist},
                        {n: kept[n][r] for n in kept if n in info.diagnosed}, status[r]) for r in range(n_runs)]
    return loop


def _inputs(filt, info, name: str, per_step: dict, checked: list) -> list[np.ndarray]:
    """The loop's inputs in the kernel's order: per-run ones stacked (runs, N, ...), per-step ones
    from the first run's checked arrays (the same for every run), constants from the filter."""
    constants = filt._measurement_buffers(name)
    arrays = []
    for n, _ in info.inputs:
        if n in ("z", "mask"):
            arrays.append(np.ascontiguousarray(np.stack([given[n] for given in checked]), dtype=float))
        elif n in info.per_step:
            source = per_step[n] if n in per_step else checked[0][n]
            fits(filt._dtype, n, source)
            arrays.append(np.ascontiguousarray(source, dtype=float))
        else:
            arrays.append(np.asfortranarray(constants[n], dtype=float))
    return arrays


def _result(filt, info, arrays, per_step: dict, given: dict, histories: dict, kept: dict, status: np.ndarray):
    """One run's RunResult, as :func:`runs.run` makes it."""
    result = runs._result(filt, histories, status)
    result.inputs = {n: a.copy() for (n, _), a in zip(info.inputs, arrays)
                     if n not in filt.spec.state and (n in ("t", "dt", "u") or n not in info.per_step)}
    result.innovations = {"kept": kept, "mask": given.get("mask")}
    return result


def _warn_default_gate(filt, name: str, results: list) -> None:
    gated = sum(r.gated_steps for r in results)
    if gated and name in filt._default_gates:
        warnings.warn(f"{filt.family} run_lockstep '{name}': {gated} updates over {len(results)} runs refused by the "
                      f"default innovation gate (chi-square probability {contract.DEFAULT_GATE_PROBABILITY!r}); set "
                      f"gate={{'{name}': None}} to fuse every update, or a probability of your own", RuntimeWarning,
                      stacklevel=3)

"""Fixed-interval smoothing of a forward run: the generated backward pass over a run's histories.

    result = ekf.run(times, z, "radar", smooth=True)      # or: smooth(ekf, ekf.run(times, z, "radar"))
    result.x, result.P                  # filtered (after each step's update)
    result.x_smooth, result.P_smooth    # smoothed (given the whole record)

The backward step is the filter's ``smooth`` kernel (codegen/families/rts.py: the EKF's RTS
smoother, the UKF's unscented RTS smoother of Särkkä 2008, the MEKF's error-state RTS;
codegen/families/cd_ekf.py: the continuous-discrete EKF's, with Phi integrated); its loop is the generated C
``<model>_<filter>_smooth_run`` (codegen/c_backend/smooth_loop.py) or, on the CasADi-VM backend,
the same kernel called step by step under the same rules. It reads the run's histories (x, P,
status) and the inputs the run recorded (:attr:`RunResult.inputs`: t, dt, u per step and the
constants Q, p, kappa), so the smoothed run is the one that was filtered even if the filter's
settings changed since. Masked and gated updates are prediction steps of the backward pass; a
step the forward run refused kept its state, so the backward pass carries the smoothed row over
it. A backward step that fails raises :class:`SymkfError` (``errors="keep"``: its row holds the
filtered estimate and its code is in ``smooth_status``).
"""
from __future__ import annotations

import ctypes
from dataclasses import dataclass, fields

import numpy as np

from symkf.codegen.spec import STATUS_GATED, STATUS_OK
from .backends import SymkfError, run_passing
from .buffers import buffer
from .runs import RunResult

#: The forward run's rows each backward step reads, and the smoothed rows it writes.
FILTERED, SMOOTHED = ("x", "P"), ("xs", "Ps")


@dataclass
class SmoothedRun(RunResult):
    """A forward run (x, P, status: :class:`RunResult`) and its fixed-interval smoothing."""

    x_smooth: np.ndarray = None        # (N, n): the estimate of step k given every measurement
    P_smooth: np.ndarray = None        # (N, n, n)
    smooth_status: np.ndarray = None   # (N,) int: 0 or the SYMKF_ERR_* code of backward step k

    def _innovation(self, key: str):
        """The forward run's (computed when first read, as the run's own)."""
        forward = self.__dict__.get("_forward")
        return forward._innovation(key) if forward is not None else super()._innovation(key)


def smooth(filt, result: RunResult, errors: str = "raise") -> SmoothedRun:
    """The fixed-interval smoothing of ``result``, a run of ``filt`` (``Filter.run`` or ``run_steps``).

    Args:
        errors: "raise" (a backward step that fails raises SymkfError) or "keep" (its row keeps the
            filtered estimate, its code is in ``smooth_status``).
    """
    kernel = filt.spec.smooth
    if not kernel:
        raise ValueError(f"smooth: filter '{filt.family}' has no smoother (its family generates none)")
    if errors not in ("raise", "keep"):
        raise ValueError("errors: expected 'raise' or 'keep'")
    info = filt._backend.kernels[kernel]
    x, P = _kernel_state(filt, result)
    arrays = _inputs(info, result, x, P)
    xs, Ps = np.zeros_like(x), np.zeros_like(P)
    codes = np.zeros(len(x), dtype=np.intc)
    status = np.ascontiguousarray(result.status, dtype=np.intc)
    if len(x):
        if filt._backend.kind == "compiled":
            _loop_in_c(filt, kernel, info, arrays, status, xs, Ps, codes)
        else:
            _loop_in_python(filt, kernel, info, arrays, status, xs, Ps, codes)
    failed = np.flatnonzero(codes != STATUS_OK)
    if failed.size and errors == "raise":
        raise SymkfError(f"{kernel}_run", int(codes[failed[-1]]),
                         f"backward step(s) {failed[::-1][:10].tolist()} failed; the run is left as it was. "
                         "smooth(..., errors='keep') returns the smoothing with those rows filtered")
    return _result(filt, result, xs, Ps, codes)


def _kernel_state(filt, result: RunResult) -> tuple[np.ndarray, np.ndarray]:
    """The run's x (N, n) and P (N, n, n) as the kernels carry them (scaled for a scaled build)."""
    if result.P is None:
        raise ValueError("smooth: the run has no covariance history")
    if not result.inputs:
        raise ValueError("smooth: this RunResult records no run inputs; smooth the result of Filter.run or run_steps")
    x, P = np.asarray(result.x, float), np.asarray(result.P, float)
    m = filt._buffers["P"].shape[0]             # the error state's dimension on a manifold
    if x.shape[1:] != (filt.n,) or P.shape != (len(x), m, m):
        raise ValueError(f"smooth: the run's x {x.shape} and P {P.shape} do not fit filter '{filt.family}' "
                         f"(x: {filt.n}, P: {m} x {m})")
    if filt._scaling is not None:
        x, P = filt._scaling.x_to_kernel(x), filt._scaling.P_to_kernel(P)
    return (np.ascontiguousarray(x, dtype=filt._dtype),
            np.ascontiguousarray(np.transpose(P, (0, 2, 1)), dtype=filt._dtype))   # each row column-major


def _inputs(info, result: RunResult, x: np.ndarray, P: np.ndarray) -> dict[str, np.ndarray]:
    """Every input of the backward step by name: the run's x, P, its per-step t, dt, u and constants."""
    arrays = {"x": x, "P": P}
    for name, _ in info.inputs:
        if name in FILTERED or name in SMOOTHED:
            continue
        if name not in result.inputs:
            raise ValueError(f"smooth: the run did not record input '{name}' of the backward step")
        arrays[name] = np.ascontiguousarray(result.inputs[name], dtype=x.dtype) if name in info.per_step \
            else np.asfortranarray(result.inputs[name], dtype=x.dtype)
    return arrays


def _loop_in_c(filt, kernel, info, arrays, status, xs, Ps, codes) -> None:
    """``<model>_<kernel>_run`` (its arguments in the order of codegen/c_backend/smooth_loop.py)."""
    backend = filt._backend
    scalar = ctypes.c_float if xs.dtype == np.float32 else ctypes.c_double
    passed, types = [], []
    for name, shape in info.inputs:
        how = run_passing(name, shape, info)
        if how == "omit" or name in SMOOTHED:
            continue
        if how == "value" and name not in info.per_step:
            passed.append(scalar(arrays[name].reshape(-1)[0]))
            types.append(scalar)
        else:
            passed.append(arrays[name].ctypes.data)
            types.append(ctypes.c_void_p)
    function = getattr(backend.lib, f"{backend.model}_{kernel}_run")
    function.argtypes = [ctypes.c_int] + types + [ctypes.c_void_p] * 4
    function.restype = ctypes.c_int
    function(len(xs), *passed, status.ctypes.data, xs.ctypes.data, Ps.ctypes.data, codes.ctypes.data)


def _loop_in_python(filt, kernel, info, arrays, status, xs, Ps, codes) -> None:
    """The backward loop for the VM backend: the same kernel and rules as the C loop (a kernel's
    outputs may alias its inputs: xs and Ps are one buffer each, in and out)."""
    buffers = {n: buffer(shape, filt._dtype) for n, shape in info.inputs + info.outputs[:-1]}
    call = filt._backend.bind(kernel, buffers)
    for name, _ in info.inputs:
        if name not in info.per_step and name not in SMOOTHED:
            buffers[name].reshape(-1, order="F")[:] = arrays[name].reshape(-1, order="F")
    last = len(xs) - 1
    xs[last], Ps[last] = arrays["x"][last], arrays["P"][last]
    for k in range(last - 1, -1, -1):
        if status[k + 1] not in (STATUS_OK, STATUS_GATED):       # the forward run kept row k as row k + 1
            xs[k], Ps[k] = xs[k + 1], Ps[k + 1]
            continue
        for name in info.per_step:          # a matrix row holds its matrix transposed (column-major)
            value = arrays[name][k if name in FILTERED else k + 1]
            buffers[name][...] = value.T if value.ndim == 2 else value
        buffers["xs"][...], buffers["Ps"][...] = xs[k + 1], Ps[k + 1].T
        codes[k] = call()
        ok = codes[k] == STATUS_OK
        xs[k] = buffers["xs"] if ok else arrays["x"][k]
        Ps[k] = buffers["Ps"].T if ok else arrays["P"][k]


def _result(filt, result: RunResult, xs: np.ndarray, Ps: np.ndarray, codes: np.ndarray) -> SmoothedRun:
    P_smooth = np.transpose(Ps, (0, 2, 1))
    if filt._scaling is not None:
        xs, P_smooth = filt._scaling.x_from_kernel(xs), filt._scaling.P_from_kernel(P_smooth)
    forward = {f.name: getattr(result, f.name) for f in fields(RunResult)}
    smoothed = SmoothedRun(**forward, x_smooth=np.asarray(xs, dtype=float), P_smooth=np.asarray(P_smooth, dtype=float),
                           smooth_status=codes)
    smoothed.__dict__["_forward"] = result           # its y, S, nis: the run's, when first read
    return smoothed


def smooth_lockstep(filt, results: list, errors: str = "raise") -> list:
    """:func:`smooth` of each of ``results`` (runs of ``filt`` over one clock with the same inputs
    but z: :meth:`Filter.run_lockstep`'s), each bit for bit what :func:`smooth` returns for it; the
    library's ``<smoother>_run_lockstep`` (codegen/c_backend/smooth_lockstep.py) does 4 backward
    passes per AVX2 vector where it has one, else each run is :func:`smooth` in turn (a library
    built with ``<family>_lockstep_vector_math``: within libmvec's round-off of :func:`smooth`)."""
    if errors not in ("raise", "keep"):
        raise ValueError("errors: expected 'raise' or 'keep'")
    loop = _lockstep_loop(filt, results)
    if loop is None:
        return [smooth(filt, result, errors) for result in results]
    states = [_kernel_state(filt, result) for result in results]
    arrays = _inputs(filt._backend.kernels[filt.spec.smooth], results[0], *states[0])
    x = np.ascontiguousarray(np.stack([s[0] for s in states]))
    P = np.ascontiguousarray(np.stack([s[1] for s in states]))
    status = np.ascontiguousarray(np.stack([r.status for r in results]), dtype=np.intc)
    xs, Ps, codes = np.zeros_like(x), np.zeros_like(P), np.zeros(status.shape, np.intc)
    loop({**arrays, "x": x, "P": P}, status, xs, Ps, codes)
    out = []
    for r, result in enumerate(results):
        failed = np.flatnonzero(codes[r] != STATUS_OK)
        if failed.size and errors == "raise":
            raise SymkfError(f"{filt.spec.smooth}_run_lockstep", int(codes[r][failed[-1]]),
                             f"run {r}: backward step(s) {failed[::-1][:10].tolist()} failed; "
                             "smooth_lockstep(..., errors='keep') returns the smoothing with those rows filtered")
        out.append(_result(filt, result, xs[r], Ps[r], codes[r]))
    return out


def _lockstep_loop(filt, results: list):
    """The compiled backward lockstep loop for ``results`` (runs that share every input but their
    histories), or None: a VM backend, a library or filter without one, runs that differ."""
    kernel, backend = filt.spec.smooth, filt._backend
    if not kernel:
        raise ValueError(f"smooth: filter '{filt.family}' has no smoother (its family generates none)")
    if (len(results) < 2 or backend.kind != "compiled" or filt._scaling is not None or filt._form is not None
            or filt._dtype != np.float64):
        return None
    function = backend.lockstep_function(kernel)
    if function is None or not _same_inputs(results):
        return None
    info = backend.kernels[kernel]
    names = [name for name, _ in info.inputs if name not in SMOOTHED]
    function.argtypes = [ctypes.c_int, ctypes.c_int] + [ctypes.c_void_p] * (len(names) + 4)
    function.restype = ctypes.c_int

    def loop(arrays: dict, status, xs, Ps, codes) -> None:
        passed = [arrays[name] for name in names]        # as _inputs made them (constants column-major)
        function(status.shape[0], status.shape[1], *[a.ctypes.data for a in passed], status.ctypes.data,
                 xs.ctypes.data, Ps.ctypes.data, codes.ctypes.data)
    return loop


def _same_inputs(results: list) -> bool:
    """Every run recorded the same inputs (t, dt, u and the constants) as the first."""
    first = results[0].inputs
    return all(r.inputs.keys() == first.keys() and r.x.shape == results[0].x.shape
               and all(np.array_equal(r.inputs[k], first[k]) for k in first) for r in results[1:])

"""Multi-sensor runs: one compiled loop over a record of several measurements at their own rates.

    result = f.run_multi(times, {"sun": z_sun, "mag": z_mag}, mask={"sun": m_sun, "mag": m_mag}, u=gyro)

Each step k predicts from times[k-1] to times[k] (the first step has dt = 0), then updates, in
the model's measurement order, with each measurement present at step k: rows where a measurement
is absent have mask 0 (or NaN z with ``nan="mask"``); a measurement not given is absent throughout.
The loop is the generated C ``<model>_<filter>_run_multi`` (codegen/c_backend/multi_loop.py) or,
on the CasADi-VM backend, the same kernels step by step; both equal the step-by-step loop
(predict, then update with each present measurement) to round-off. Every measurement's array is
checked by the rules of one run (:func:`symkf.runtime.runs.series`).
"""
from __future__ import annotations

import ctypes
from dataclasses import dataclass, field

import numpy as np

from symkf.codegen.c_backend.multi_loop import multi_arguments
from symkf.codegen.spec import STATUS_GATED, STATUS_OK, Arg
from . import contract, innovations
from .buffers import buffer
from .runs import REFUSED_POLICIES, RunRefused, RunResult, series, steps_from_clock


@dataclass
class MultiRunResult(RunResult):
    """A multi-sensor run: x, P per step; ``status`` is each step's prediction code (a failed
    prediction kept the state: what a smoother reads), ``update_status`` each measurement's update
    code per step (SYMKF_OK where absent), ``present`` where it updated; ``y``, ``S``, ``nis`` and
    ``nis_dof`` are dicts by measurement (NaN and 0 dof where absent)."""

    update_status: dict = field(default_factory=dict)
    present: dict = field(default_factory=dict)

    @property
    def refused_steps(self) -> np.ndarray:
        """Steps whose prediction or any update was refused (gated updates are not refusals)."""
        return np.flatnonzero(self._refused_codes() != 0)

    def refused_codes(self) -> np.ndarray:
        return self._refused_codes()[self.refused_steps]

    def _refused_codes(self) -> np.ndarray:
        codes = np.where(self.status == STATUS_GATED, 0, self.status)
        for update in self.update_status.values():
            codes = np.where(codes == 0, np.where(update == STATUS_GATED, 0, update), codes)
        return codes

    def _innovation(self, key: str):
        """By measurement: computed on first use from each one's histories (NaN where absent)."""
        if "_innovations" not in self.__dict__:
            by = {}
            for m, raw in self.innovations.items():
                codes = np.where(self.present[m], self.update_status[m], -1)       # absent: no innovation
                by[m] = innovations.of_run(raw["kept"], raw["mask"], codes)
            self.__dict__["_innovations"] = {k: {m: v.get(k) for m, v in by.items()}
                                             for k in ("y", "S", "nis", "nis_dof")}
        return self.__dict__["_innovations"].get(key)


def run_multi(filt, times, z: dict, q: dict | None = None, mask: dict | None = None, u=None,
              nan: str = "raise", refused: str = "raise") -> MultiRunResult:
    """The multi-sensor run of ``filt`` (see the module docstring); x, P and t end at the last step.
    times[0] is not before the filter's time (the first step predicts from it); a refused step
    raises :class:`~symkf.runtime.runs.RunRefused` (the filter as before) unless ``refused`` is
    "continue", as :meth:`Filter.run <symkf.runtime.filters.Filter.run>`."""
    if refused not in REFUSED_POLICIES:
        raise ValueError(f"refused: expected one of {REFUSED_POLICIES}, got {refused!r}")
    spec = filt.spec
    if not spec.predict or len(spec.update) < 2:
        raise ValueError(f"run_multi: filter '{filt.family}' has no separate prediction and updates for two or "
                         "more measurements; use run()")
    unknown = sorted(set(z) - set(spec.update))
    if unknown or not z:
        raise ValueError(f"z: measurement(s) {unknown or '(none)'} not among {list(spec.update)}")
    for name, given in (("q", q), ("mask", mask)):
        if given and set(given) - set(z):
            raise ValueError(f"{name}: measurement(s) {sorted(set(given) - set(z))} have no z")
    times = contract.run_times(times)
    n_steps = times.size
    per_step = steps_from_clock(filt, times, "run_multi")
    records = {m: _record(filt, m, n_steps, z, q or {}, mask or {}, u, nan) for m in spec.update}
    per_step["u"] = next(iter(records.values())).get("u")
    kernels = {k: _described(filt._backend.kernels[k]) for k in [spec.predict, *spec.update.values()]}
    arguments = multi_arguments(spec, kernels)
    arrays = _arrays(filt, arguments, per_step, records)
    filt._fast.before_write()
    if filt._backend.kind == "compiled":
        _loop_in_c(filt, arguments, arrays)
    else:
        _loop_in_python(filt, kernels, arguments, arrays)
    result = _result(filt, arguments, arrays, per_step, records)
    if refused == "raise" and result.refused_steps.size:
        raise RunRefused(f"{filt.family} run_multi", result)
    _adopt(filt, arrays, per_step, n_steps)
    return result


def _record(filt, m: str, n_steps: int, z: dict, q: dict, mask: dict, u, nan: str) -> dict:
    """Measurement ``m``'s checked per-step arrays; all-masked zeros if it is not in the record."""
    if m in z:
        return series(filt, m, n_steps, {"z": z[m], "q": q.get(m), "mask": mask.get(m)}, u, nan)
    buffers = filt.measurements[m]
    absent = {"z": np.zeros((n_steps,) + buffers["z"].shape), "q": np.zeros((n_steps,) + buffers["q"].shape),
              "mask": np.zeros((n_steps,) + buffers["mask"].shape)}
    return series(filt, m, n_steps, absent, u, nan)


def _described(info):
    """A manifest kernel as the C writer's argument rules read it (inputs and outputs as Args)."""
    class Described:
        inputs = [Arg(n, tuple(s)) for n, s in info.inputs]
        outputs = [Arg(n, tuple(s)) for n, s in info.outputs]
    return Described


def _arrays(filt, arguments, per_step: dict, records: dict) -> dict[str, np.ndarray]:
    """Every argument of the loop as a contiguous array, by C name (the state from the filter)."""
    n_steps, dtype = per_step["dt"].size, filt._dtype
    arrays = {}
    for c_name, name, m, kind, size in arguments:
        if kind == "per_step":
            source = per_step[name] if m is None else records[m][name]
            arrays[c_name] = np.ascontiguousarray(np.reshape(source, (n_steps, -1)), dtype=dtype)
        elif kind in ("value", "array", "initial"):
            source = filt._buffers[name] if m is None else filt.measurements[m][name]
            arrays[c_name] = np.array(source, dtype=dtype).reshape(-1, order="F")
        elif kind == "history":
            arrays[c_name] = np.zeros((n_steps, size), dtype)
        else:
            arrays[c_name] = np.zeros((n_steps, size), np.intc)
    return arrays


def _loop_in_c(filt, arguments, arrays) -> None:
    backend = filt._backend
    scalar = ctypes.c_float if filt._dtype == np.float32 else ctypes.c_double
    function = getattr(backend.lib, f"{backend.model}_{filt.spec.name}_run_multi")
    function.argtypes = [ctypes.c_int] + [scalar if kind == "value" else ctypes.c_void_p
                                          for _, _, _, kind, _ in arguments]
    function.restype = ctypes.c_int
    passed = [scalar(arrays[c][0]) if kind == "value" else arrays[c].ctypes.data for c, _, _, kind, _ in arguments]
    function(len(arrays["t"]), *passed)


def _loop_in_python(filt, kernels, arguments, arrays) -> None:
    """The loop for the VM backend: the prediction and present updates, under the C loop's rules."""
    spec, dtype = filt.spec, filt._dtype
    names = list(spec.update)
    shared = {a.name: buffer(a.shape, dtype) for k in kernels.values() for a in k.inputs + k.outputs[:-1]
              if a.name not in ("q", "z", "mask", "R", "gate", "y", "S")}
    own = {m: {a.name: buffer(a.shape, dtype) for a in kernels[spec.update[m]].inputs + kernels[spec.update[m]].outputs[:-1]
               if a.name in ("q", "z", "mask", "R", "gate", "y", "S")} for m in names}
    predict = filt._backend.bind(spec.predict, shared)
    updates = {m: filt._backend.bind(spec.update[m], {**shared, **own[m]}) for m in names}
    fixed = [(c, n, m) for c, n, m, kind, _ in arguments if kind in ("value", "array", "initial")]
    for c, n, m in fixed:
        (shared if m is None else own[m])[n].reshape(-1, order="F")[:] = arrays[c]
    status = arrays["status_hist"]
    for k in range(len(arrays["t"])):
        state = {n: shared[n].copy() for n in ("x", "P")}
        shared["t"][...], shared["dt"][...] = arrays["t"][k], arrays["dt"][k]
        if "u" in arrays:
            shared["u"][...] = arrays["u"][k]
        status[k] = predict()
        if status[k, 0] != STATUS_OK:
            for n in ("x", "P"):
                shared[n][...] = state[n]
        else:
            shared["t"][...] = arrays["t"][k] + arrays["dt"][k]
            for j, m in enumerate(names):
                status[k, j + 1] = _update_once(updates[m], own[m], arrays, m, k)
        arrays["x_hist"][k] = shared["x"].reshape(-1, order="F")
        arrays["P_hist"][k] = shared["P"].reshape(-1, order="F")
        for j, m in enumerate(names):
            if status[k, 0] == STATUS_OK and status[k, j + 1] in (STATUS_OK, STATUS_GATED):
                for n in ("y", "S"):
                    if f"{n}_{m}_hist" in arrays:
                        arrays[f"{n}_{m}_hist"][k] = own[m][n].reshape(-1, order="F")


def _update_once(call, own: dict, arrays, m: str, k: int) -> int:
    """Measurement ``m``'s update at step k if present (a mask entry > 0.5), else SYMKF_OK."""
    mask = arrays[f"mask_{m}"][k]
    if not np.any(mask > 0.5):
        return STATUS_OK
    for n in ("q", "z", "mask"):
        if f"{n}_{m}" in arrays:
            own[n].reshape(-1, order="F")[:] = arrays[f"{n}_{m}"][k]
    return call()


def _adopt(filt, arrays, per_step: dict, n_steps: int) -> None:
    """The filter's x, P, t (and held u) set to the run's last step."""
    if not n_steps:
        return
    shapes = {n: filt._buffers[n].shape for n in ("x", "P")}
    filt._buffers["x"][...] = arrays["x_hist"].reshape((n_steps,) + shapes["x"])[-1]
    filt._buffers["P"][...] = arrays["P_hist"].reshape((n_steps,) + shapes["P"][::-1]).transpose(0, 2, 1)[-1]
    if per_step.get("u") is not None and filt._buffers["u"].size:
        filt._buffers["u"][:] = per_step["u"][-1]
        filt._u_given = True
    filt.t = float(per_step["t"][-1] + per_step["dt"][-1])


def _result(filt, arguments, arrays, per_step: dict, records: dict) -> MultiRunResult:
    """The run's histories as a MultiRunResult (the filter unchanged)."""
    spec, n_steps = filt.spec, arrays["t"].shape[0]
    shapes = {n: filt._buffers[n].shape for n in ("x", "P")}
    x = arrays["x_hist"].reshape((n_steps,) + shapes["x"])
    P = arrays["P_hist"].reshape((n_steps,) + shapes["P"][::-1]).transpose(0, 2, 1)
    if filt._scaling is not None:
        x, P = filt._scaling.x_from_kernel(x), filt._scaling.P_from_kernel(P)
    status = arrays["status_hist"]
    names = list(spec.update)
    present = {m: np.any(records[m]["mask"].reshape(n_steps, -1) > 0.5, axis=1) & (status[:, 0] == STATUS_OK)
               for m in names}
    raw = {m: {"kept": {n: arrays[f"{n}_{m}_hist"] for n in ("y", "S") if f"{n}_{m}_hist" in arrays},
               "mask": records[m]["mask"]} for m in names}
    inputs = {c: arrays[c].copy() for c, n, m, kind, _ in arguments if m is None and kind in ("per_step", "value", "array")}
    inputs.update({n: np.array(filt._buffers[n]) for n in ("p", "Q", "kappa") if n in filt._buffers})
    inputs["t"], inputs["dt"] = per_step["t"], per_step["dt"]
    return MultiRunResult(np.asarray(x, float), np.asarray(P, float), status[:, 0].copy(), inputs, raw,
                          update_status={m: status[:, j + 1].copy() for j, m in enumerate(names)}, present=present)

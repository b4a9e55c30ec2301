"""One call of a :class:`~symkf.runtime.filters.Filter` on its Python path: its inputs checked
against the filter's buffers before anything is written (the measurement named, the input ``u``,
a measurement's z, q and mask: the rules of :mod:`symkf.runtime.contract`, the NaN policy, the
element type of a float build), then written, and the kernel's status code turned into the
call's result or its :class:`~symkf.runtime.backends.SymkfError`; and the constructor's initial
values, written through the filter's setters (a user's checks)."""
from __future__ import annotations

import numpy as np

from symkf.codegen.spec import STATUS_GATED, STATUS_NONFINITE
from . import contract
from .backends import SymkfError
from .buffers import fits


#: ``gate="none"``: no innovation gate on any measurement (as a paper that fuses every update).
NO_GATES = "none"


def initialise(filt, x0, P0, Q, R: dict | None, p, gate: dict | None, scalars: dict) -> None:
    """x, P, Q, p, the kernels' scalar options (defaults from the spec), R per measurement
    (default diag(sigma^2) from the model) and the innovation gates of a new filter."""
    shared, spec, model = filt._buffers, filt.spec, filt.model
    filt.x = x0
    if "P" in shared:
        filt.P = P0
    if "Q" in shared:
        filt.Q = Q
    if "p" in shared:
        filt.p = [v["default"] for v in model["params"]] if p is None else p
    known = {name: value for name, value in spec.defaults.items()}
    known.update(contract.known_keys("options", scalars, spec.defaults))
    for name, value in known.items():
        shared[name][0] = fits(filt._dtype, name, contract.real(name, value))
    R = contract.known_keys("R", R, spec.measurements)
    for name in spec.measurements:
        if "R" in filt.measurements[name]:
            filt.set_R(name, R[name] if name in R else np.diag(np.square(model["measurements"][name]["sigma"])))
    gate = dict.fromkeys(spec.measurements) if gate == NO_GATES else contract.known_keys("gate", gate, spec.measurements)
    for name in spec.measurements:
        if name in gate:
            value = gate[name]
            filt.set_gate(name, **(value if isinstance(value, dict) else {"probability": value}))
        elif "gate" in filt.measurements[name]:
            filt.set_gate(name, contract.DEFAULT_GATE_PROBABILITY)
            filt._default_gates.add(name)


def measurement_name(filt, measurement: str | None, kind: str, call: str | None = None) -> str:
    """The measurement a ``kind`` ("update" or "step") call of ``filt`` names; None only where the
    filter has one measurement (with several, z could be any of them: the caller must say)."""
    names = list(getattr(filt.spec, kind))
    if measurement is None:
        if len(filt.spec.measurements) == 1 and names:
            return names[0]
        raise ValueError(f"measurement: model '{filt.model['name']}' has measurements {names}; name the one z "
                         f"is, e.g. {_example(call or kind, names[0])}")
    if measurement not in names:
        raise ValueError(f"measurement: '{measurement}' is not one of {names} (filter '{filt.family}', {kind})")
    return measurement


def _example(kind: str, name: str) -> str:
    return {"update": f"update(z, '{name}')", "step": f"step(t, dt, z, '{name}')",
            "run": f"run(times, z, '{name}')", "run_steps": f"run_steps(dt, z, '{name}')"}.get(kind, f"'{name}'")


#: The value of ``u`` that keeps the input of the previous call (said on purpose, never implied).
HOLD = "hold"


def has_inputs(filt) -> bool:
    return "u" in filt._buffers and filt._buffers["u"].size > 0


def reads_u(filt, kernel: str) -> bool:
    """Whether compiled ``kernel`` of ``filt`` reads the input u (an update's h may not)."""
    info = filt._backend.kernels[kernel]
    return any(name == "u" for name, _ in info.inputs) and "u" not in info.ignores


def _input_given(filt) -> bool:
    """Whether a call has given u yet (every step the C fast path took did: it declines a None u)."""
    return filt._u_given or filt.fast_calls > 0


def u_input(filt, u, call: str, reads_u: bool = True) -> np.ndarray | None:
    """The checked input ``u`` of a ``call`` (None: keep the held one, when the caller said
    ``u="hold"`` or the call's kernel does not read u, ``reads_u`` False). A model with inputs
    needs u on every call that propagates (predict, step, run): a forgotten u would otherwise
    propagate with zeros or a stale sample. An update evaluates h at the end of the interval the
    last call propagated over, with that call's input; before any input was given it needs u too."""
    if not has_inputs(filt):
        if u is not None:
            raise ValueError(f"u: model '{filt.model['name']}' has no inputs")
        return None
    if isinstance(u, str) and u == HOLD:
        if not _input_given(filt):
            raise ValueError(f"u: '{HOLD}' keeps the last input, but model '{filt.model['name']}' has been given "
                             "none yet; pass u=... on this call")
        return None
    if u is None:
        if not reads_u or (call == "update" and _input_given(filt)):
            return None
        names = [f"{v['name']} [{v.get('unit', '-')}]" for v in filt.model["inputs"]]
        raise ValueError(f"u: model '{filt.model['name']}' has inputs {names}; {call} needs u=... on every call "
                         f"(u='hold' keeps the last input, now {filt._buffers['u'].tolist()})")
    return fits(filt._dtype, "u", contract.finite_array("u", u, filt._buffers["u"].shape))


def measurement_values(filt, name: str, given: dict, nan: str) -> dict[str, np.ndarray]:
    """Validated per-call measurement inputs (z, q, mask or a family's own); writes nothing."""
    nan = contract.nan_policy(nan) if nan != "raise" else nan
    buffers = filt.measurements[name]
    values = {}
    for key, value in given.items():
        if key not in buffers:
            if value is not None:
                raise ValueError(f"{key}: measurement '{name}' of filter '{filt.family}' takes no {key}")
            continue
        if key == "mask":
            values[key] = None if value is None else contract.mask(value, buffers[key].shape)
        elif key == "q" and value is None and buffers[key].size:
            params = [v["name"] for v in filt.model["measurements"][name]["params"]]
            raise ValueError(f"q: measurement '{name}' needs its parameters {params} (q=...) on every call")
        elif value is not None or buffers[key].size:
            values[key] = contract.exact_array(key, value, buffers[key].shape)
    if nan == "mask":
        values = mask_nonfinite(values, buffers)
    for key, value in values.items():
        if value is not None:
            fits(filt._dtype, key, value)
    return values


def mask_nonfinite(values: dict, buffers: dict) -> dict:
    """nan="mask": non-finite measurement components are masked (the whole measurement when
    its mask is one number)."""
    z = values["z"]
    finite = np.isfinite(z)
    mask = np.ones(buffers["mask"].shape) if values.get("mask") is None else values["mask"]
    values["mask"] = mask * (finite if mask.shape == finite.shape else float(finite.all()))
    values["z"] = np.where(finite, z, 0.0)
    return values


def write_time(filt, t: float, dt: float | None, u) -> None:
    """Time (and input) of a call: checked for the buffers' type before anything is written;
    the measurement's values are written after this (they are already checked)."""
    fits(filt._dtype, "t", t)
    fits(filt._dtype, "dt", dt if dt is not None else 0.0)
    filt._fast.before_write()
    shared = filt._buffers
    if "t" in shared:
        shared["t"][0] = t
    if dt is not None:
        shared["dt"][0] = dt
    if u is not None:
        shared["u"][:] = u
        filt._u_given = True


def write_measurement(filt, name: str, values: dict) -> None:
    """The checked values of measurement ``name`` into its buffers (an omitted mask: all ones)."""
    filt._fast.before_write()
    buffers = filt.measurements[name]
    for key, value in values.items():
        if key == "mask":
            buffers["mask"][...] = 1.0 if value is None else value
        else:
            buffers[key][...] = value


def check(filt, code: int, what: str, measurement: str | None = None) -> int:
    """``code`` if it is 0 or SYMKF_GATED, else the :class:`SymkfError` of call ``what``."""
    if code == 0 or code == STATUS_GATED:
        return code
    detail = ""
    if code == STATUS_NONFINITE and measurement is not None:
        detail = nonfinite_detail(filt.measurements[measurement])
    raise SymkfError(f"{filt.family} {what}", code, detail)


def nonfinite_detail(buffers: dict) -> str:
    """Which used components of a measurement's z are NaN/Inf (for a SYMKF_ERR_NONFINITE), or ""."""
    if "z" not in buffers:
        return ""
    mask = buffers.get("mask", np.ones(1))
    bad = ~np.isfinite(buffers["z"]) & (mask > 0.5 if mask.shape == buffers["z"].shape else mask[0] > 0.5)
    if not bad.any():
        return ""
    return f"measurement z has NaN/Inf at components {np.flatnonzero(bad).tolist()}; pass nan='mask' to skip them"

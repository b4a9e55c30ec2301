"""The numpy buffers a :class:`~symkf.runtime.filters.Filter` binds its kernels to, made once from
its :class:`~symkf.codegen.spec.FilterSpec`: one per argument name of its kernels, the
per-measurement ones (the spec's measurement inputs and diagnostics) once per measurement."""
from __future__ import annotations

import numpy as np

from symkf.codegen.spec import FilterSpec


def buffer(shape: tuple[int, int], dtype=np.float64) -> np.ndarray:
    """A zeroed column-major buffer: (r,) for a column vector, (r, c) for a matrix."""
    return np.zeros(shape[0], dtype) if shape[1] == 1 else np.zeros(shape, dtype, order="F")


def kernel_roles(spec: FilterSpec) -> list[tuple[str, str | None]]:
    """(kernel, measurement it reads or None) of every kernel of the filter."""
    # a prediction that reads a measurement input (the augmented UKF's R) reads the first one's
    roles = [(spec.predict, spec.measurements[0])] if spec.predict else []
    roles += [(k, m) for m, k in spec.update.items()]
    return roles + [(k, m) for m, k in spec.step.items()]


def make_buffers(spec: FilterSpec, kernels: dict, dtype) -> tuple[dict, dict[str, dict]]:
    """(shared buffers, {measurement: its buffers}), by argument name; every mask starts at ones."""
    shared: dict[str, np.ndarray] = {}
    measurements: dict[str, dict[str, np.ndarray]] = {m: {} for m in spec.measurements}
    per_measurement = set(spec.measurement_inputs) | set(spec.diagnostics)
    for kernel, measurement in kernel_roles(spec):
        info = kernels[kernel]
        for name, shape in info.inputs + info.outputs[:-1]:
            if measurement is not None and name in per_measurement:
                measurements[measurement].setdefault(name, buffer(shape, dtype))
            else:
                shared.setdefault(name, buffer(shape, dtype))
    for buffers in measurements.values():
        if "mask" in buffers:
            buffers["mask"][:] = 1.0
    return shared, measurements


def fits(dtype, name: str, value, where: str = ""):
    """``value`` unchanged if buffers of element type ``dtype`` hold it; for a float build, ValueError
    (nothing written, no NumPy overflow warning) if a finite value overflows float (|value| >
    3.4e38), checked before any buffer of the call is written. NaN and Inf pass: the contract
    and the kernels decide about them."""
    if dtype == np.float64:
        return value
    array = np.asarray(value, dtype=float)
    with np.errstate(over="ignore"):
        converted = array.astype(dtype)
    if np.any(np.isinf(converted) & np.isfinite(array)):
        raise ValueError(f"{name}: a value overflows {dtype.name} (|value| > "
                         f"{np.finfo(dtype).max:.3g}{where}), the range of this float build")
    return value

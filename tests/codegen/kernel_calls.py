"""Calling a compiled kernel the two ways the run-loop tests compare: its C run loop over every
step at once, and its ``_v`` entry one step at a time, x and P updated in place (as a Filter binds
them: a refused step leaves them as they were)."""
import numpy as np


def run_in_c(backend, kernel: str, values: dict, steps: int):
    """(the run's code, the per-step codes, x history, P history) of ``kernel``'s C run loop."""
    info = backend.kernels[kernel]
    arrays = {name: np.ascontiguousarray(values[name].reshape(steps, -1)) if name in info.per_step
              else np.asfortranarray(values[name].reshape(shape, order="F")) for name, shape in info.inputs}
    x_hist, P_hist = np.zeros((steps, values["x"].size)), np.zeros((steps, values["P"].size))
    status = np.zeros(steps, dtype=np.int32)
    code = backend.run_function(kernel)(steps, *[arrays[name].ctypes.data for name, _ in info.inputs],
                                        x_hist.ctypes.data, P_hist.ctypes.data, status.ctypes.data)
    return code, status.tolist(), x_hist, P_hist


def step_by_step(backend, kernel: str, values: dict, steps: int) -> tuple[list[int], np.ndarray, np.ndarray]:
    """(codes, x history, P history) of ``steps`` calls of ``kernel``'s ``_v`` entry."""
    info = backend.kernels[kernel]
    buffers = {name: np.zeros(shape, order="F") for name, shape in info.inputs + info.outputs[:-1]}
    buffers["x"][:, 0], buffers["P"][...] = values["x"], values["P"]
    call = backend.bind(kernel, buffers)
    codes, xs, Ps = [], [], []
    for k in range(steps):
        for name, shape in info.inputs:
            if name in ("x", "P") or not np.prod(shape):
                continue
            value = values[name][k] if name in info.per_step else values[name]
            buffers[name][...] = np.reshape(value, shape, order="F")
        codes.append(call())
        xs.append(buffers["x"][:, 0].copy())
        Ps.append(buffers["P"].ravel(order="F").copy())
    return codes, np.array(xs), np.array(Ps)

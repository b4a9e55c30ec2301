"""Every generated C function equals CasADi's own evaluation of the same Function (<= 1e-12 rel)."""
import numpy as np

from symkf.models import launcher as L


def _random_inputs(kernel, rng):
    """Valid random inputs: a state near the launcher's flight envelope, SPD matrices."""
    values = {}
    x = L.initial_state() + np.array([3000.0, -1.0, 0.1, 2e5, 0.02, -0.05]) * rng.uniform(0.2, 1.0, 6)
    for arg in kernel.inputs:
        n, m = arg.shape
        if arg.name == "x":
            values["x"] = x
        elif arg.name in ("P", "Q", "R"):
            A = rng.normal(size=(n, n))
            scale = np.array([1.0, 1e-3, 1e-3, 10.0, 1e-5, 1e-5])[:n] if arg.name != "R" else np.array([10.0, 1e-4, 1e-4])
            values[arg.name] = np.diag(scale) @ (A @ A.T + n * np.eye(n)) @ np.diag(scale)
        elif arg.name == "t":
            values["t"] = np.array([rng.uniform(0, 430)])
        elif arg.name == "dt":
            values["dt"] = np.array([0.05])
        elif arg.name == "q":
            values["q"] = L.station_params(int(rng.integers(1, 4)))
        elif arg.name == "z":
            values["z"] = np.array([2e5, 0.3, 2.9])
        elif arg.name == "mask":
            values["mask"] = (rng.uniform(size=n) > 0.3).astype(float)
        elif arg.name == "kappa":
            values["kappa"] = np.array([rng.uniform(0, 3)])
        elif arg.name == "p":
            values["p"] = np.array([v for v in L.GUIDANCE.values()][1:]) * rng.uniform(0.9, 1.1, n)
        else:
            values[arg.name] = rng.normal(size=(n, m))
    return values


def test_every_kernel_matches_casadi(launcher_compiled, launcher_bundle):
    rng = np.random.default_rng(1)
    backend = launcher_compiled.backend
    assert backend.kind == "compiled"
    for kernel in launcher_bundle.kernels:
        for trial in range(5):
            inputs = _random_inputs(kernel, rng)
            expected = kernel.function.call([inputs[a.name].reshape(a.shape, order="F") for a in kernel.inputs])
            buffers = {a.name: np.asfortranarray(np.reshape(inputs[a.name], a.shape, order="F"), dtype=float)
                       for a in kernel.inputs}
            outputs = {a.name: np.zeros(a.shape, order="F") for a in kernel.outputs[:-1]}
            code = _call_with_separate_outputs(backend, kernel, buffers, outputs)
            assert code == int(expected[-1]), kernel.name
            if code:
                continue
            for a, value in zip(kernel.outputs[:-1], expected[:-1]):
                got, want = outputs[a.name], np.asarray(value)
                # element-wise relative error, floored at the array's own scale (entries that are 0)
                floor = max(np.max(np.abs(want)), 1e-300)
                rel = np.max(np.abs(got - want) / np.maximum(np.abs(want), floor * 1e-3))
                assert rel <= 1e-12, f"{kernel.name}.{a.name}: relative error {rel:.2e}"


def _call_with_separate_outputs(backend, kernel, inputs, outputs):
    """Call <model>_<kernel> through ctypes with distinct input and output pointers."""
    import ctypes
    fn = getattr(backend.lib, f"launcher_{kernel.name}")
    fn.restype = ctypes.c_int
    ptrs = [inputs[a.name].ctypes.data for a in kernel.inputs] + \
           [outputs[a.name].ctypes.data for a in kernel.outputs[:-1]]
    fn.argtypes = [ctypes.c_void_p] * len(ptrs)
    return fn(*ptrs)

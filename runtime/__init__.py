"""The hot path: load a model's compiled library and run its filters from Python.

    from symkf.runtime import load
    launcher = load("launcher")            # builds build/launcher/ first if it is stale
    ekf = launcher.ekf(x0, P0, Q)          # x, P live in buffers the C code writes into
    ekf.predict(t, dt); ekf.update(z, q=station)

Without a C compiler, ``load`` warns and evaluates the very same CasADi Functions in CasADi's
virtual machine (``backend.kind == "casadi-vm"``).
"""
from __future__ import annotations

from symkf.codegen import CompilerNotFound, build_model, generate, make_config
from .backends import CompiledBackend, StaleLibraryError, SymkfError, VirtualMachineBackend
from .filters import KalmanFilter, RunResult

__all__ = ["CompiledModel", "KalmanFilter", "RunResult", "StaleLibraryError", "SymkfError", "load"]


class CompiledModel:
    """A model's kernels, callable from Python, plus factories for its filters."""

    def __init__(self, name: str, backend, description: dict):
        self.name = name
        self.backend = backend
        self.model = description

    def filter(self, family: str, x0, P0, Q, **options) -> KalmanFilter:
        if f"{family}_predict" not in self.backend.kernels:
            raise ValueError(f"model '{self.name}' has no '{family}' filter; it was generated with "
                             f"{sorted({k.split('_')[0] for k in self.backend.kernels})}")
        return KalmanFilter(self, family, x0, P0, Q, **options)

    def ekf(self, x0, P0, Q, **options) -> KalmanFilter:
        """Extended Kalman filter (Joseph-form update). Options: R, p."""
        return self.filter("ekf", x0, P0, Q, **options)

    def ukf(self, x0, P0, Q, kappa: float = 0.0, **options) -> KalmanFilter:
        """Unscented Kalman filter, Julier sigma points with ``kappa``. Options: R, p."""
        return self.filter("ukf", x0, P0, Q, kappa=kappa, **options)


def load(name: str, backend: str = "auto", **overrides) -> CompiledModel:
    """Build if stale, then load. ``backend``: "auto", "compiled" or "casadi-vm"."""
    if backend not in ("auto", "compiled", "casadi-vm"):
        raise ValueError("backend: expected 'auto', 'compiled' or 'casadi-vm'")
    if backend != "casadi-vm":
        try:
            result = build_model(name, **overrides)
        except CompilerNotFound as exc:
            if backend == "compiled":
                raise
            return _vm_model(name, reason=str(exc), **overrides)
        compiled = CompiledBackend.from_directory(result.directory)
        return CompiledModel(name, compiled, compiled.manifest["description"])
    return _vm_model(name, reason="", **overrides)


def _vm_model(name: str, reason: str, **overrides) -> CompiledModel:
    bundle = generate(name, make_config(name, **overrides))
    return CompiledModel(name, VirtualMachineBackend(bundle, reason), bundle.description)

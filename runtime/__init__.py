"""The hot path: load a model's compiled library and run its filters from Python.

    from symkf.runtime import load
    launcher = load("launcher")            # a paper model; builds its folder first if it is stale
    tracker = load("path/to/tracker.py")   # or any file / module whose build() returns a Model
    ekf = launcher.ekf(x0, P0, Q)          # x, P live in buffers the C code writes into
    ekf.predict(t, dt); ekf.update(z, q=station)

A model file is executed afresh on every ``load`` (an edit gives the new equations); the library
is opened only after its SHA-256 matches the manifest. Without a C compiler, ``load`` uses an
up-to-date compiled library if there is one, else warns and evaluates the very same CasADi
Functions in CasADi's virtual machine (``backend.kind == "casadi-vm"``).
"""
from __future__ import annotations

from symkf.codegen import CompilerNotFound, build_model, generate, make_config
from symkf.models import get_model
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


def load(model, backend: str = "auto", **overrides) -> CompiledModel:
    """Build if stale, then load. ``model``: a paper model's short name ("launcher"), a file path
    ("path/to/tracker.py"), a module name ("mypkg.tracker"), a module or a Model.
    ``backend``: "auto", "compiled" or "casadi-vm"; ``overrides``: codegen options."""
    if backend not in ("auto", "compiled", "casadi-vm"):
        raise ValueError("backend: expected 'auto', 'compiled' or 'casadi-vm'")
    model = get_model(model)
    if backend != "casadi-vm":
        try:
            result = build_model(model, **overrides)
        except CompilerNotFound as exc:
            if backend == "compiled":
                raise
            return _vm_model(model, reason=str(exc), **overrides)
        compiled = CompiledBackend.from_directory(result.directory)
        return CompiledModel(model.name, compiled, compiled.manifest["description"])
    return _vm_model(model, reason="", **overrides)


def _vm_model(model, reason: str, **overrides) -> CompiledModel:
    bundle = generate(model, make_config(model, **overrides))
    return CompiledModel(model.name, VirtualMachineBackend(bundle, reason), bundle.description)

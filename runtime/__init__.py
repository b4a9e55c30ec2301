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

import time

from symkf.codegen import CompilerNotFound, FilterSpec, build_validated, config_for, generate_validated
from symkf.models import get_model
from .backends import CompiledBackend, StaleLibraryError, SymkfError, VirtualMachineBackend
from .contract import DEFAULT_GATE_PROBABILITY
from .filters import Filter
from .runs import RunRefused, RunResult
from .smoothing import SmoothedRun, smooth, smooth_lockstep

__all__ = ["CompiledModel", "DEFAULT_GATE_PROBABILITY", "Filter", "RunRefused", "RunResult", "SmoothedRun",
           "StaleLibraryError", "SymkfError", "load", "smooth", "smooth_lockstep"]


class CompiledModel:
    """A model's kernels, callable from Python, plus its filters (from the manifest's specs)."""

    def __init__(self, name: str, backend, description: dict, filters: list[FilterSpec], build=None):
        self.name = name
        self.backend = backend
        self.model = description
        self.filters = {spec.name: spec for spec in filters}
        #: The BuildResult behind a compiled model (paths, up_to_date, timings); None for the VM.
        self.build = build

    def filter(self, name: str, x0, P0=None, Q=None, **options) -> Filter:
        """The generated filter ``name`` (see ``self.filters``); x0, P0, Q and the options (R, p,
        gate, t0, scalars such as kappa) as :class:`Filter`, which says what P0 and Q mean for
        each family (the state's covariance, or a manifold filter's error-state chart)."""
        if name not in self.filters:
            raise ValueError(f"model '{self.name}' has no '{name}' filter; it has {sorted(self.filters)}")
        return Filter(self, name, x0, P0, Q, **options)

    def ekf(self, x0, P0, Q, **options) -> Filter:
        """Extended Kalman filter (Joseph-form update). Options: R, p, gate, t0 (:class:`Filter`)."""
        return self.filter("ekf", x0, P0, Q, **options)

    def ukf(self, x0, P0, Q, kappa: float = 0.0, **options) -> Filter:
        """Unscented Kalman filter, Julier sigma points with ``kappa``. Options: R, p, gate, t0."""
        return self.filter("ukf", x0, P0, Q, kappa=kappa, **options)


def load(model, backend: str = "auto", **overrides) -> CompiledModel:
    """Build if stale, then load. ``model``: a paper model's short name ("launcher"), a file path
    ("path/to/tracker.py"), a module name ("mypkg.tracker"), a module or a Model.
    ``backend``: "auto", "compiled" or "casadi-vm"; ``overrides``: codegen options."""
    if backend not in ("auto", "compiled", "casadi-vm"):
        raise ValueError("backend: expected 'auto', 'compiled' or 'casadi-vm'")
    start = time.perf_counter()
    model = get_model(model)
    if backend != "casadi-vm":
        try:
            result = build_validated(model, start=start, **overrides)          # get_model validated it
        except CompilerNotFound as exc:
            if backend == "compiled":
                raise
            return _vm_model(model, reason=str(exc), **overrides)
        for attempt in range(3):        # the build checked can be pruned or damaged before it is opened
            try:
                compiled = CompiledBackend.from_build(result)
                break
            except (FileNotFoundError, StaleLibraryError):
                if attempt == 2:
                    raise
                result = build_validated(model, start=start, **overrides)
        return CompiledModel(model.name, compiled, compiled.manifest["description"],
                             [FilterSpec.from_dict(f) for f in compiled.manifest["filters"]], result)
    return _vm_model(model, reason="", **overrides)


def _vm_model(model, reason: str, **overrides) -> CompiledModel:
    """The VM backend; refused for a single-precision configuration: CasADi's VM evaluates in
    double only, so it would give double's numbers under a float build's name."""
    config = config_for(model, **overrides)                          # get_model validated it
    if config.precision != "double":
        why = f" ({reason})" if reason else ""
        error = CompilerNotFound if reason else ValueError
        raise error(f"precision='{config.precision}' needs the compiled C: CasADi's virtual machine evaluates "
                    f"in double only{why}")
    bundle = generate_validated(model, config)
    return CompiledModel(model.name, VirtualMachineBackend(bundle, reason), bundle.description, bundle.filters)

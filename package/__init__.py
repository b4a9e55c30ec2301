"""symkf: filters for vehicles written once as symbolic equations, generated into C.

A model author writes the equations of a vehicle and its sensors once, in CasADi
(:mod:`symkf.models`); symkf derives the Jacobians, the discretisation and whole filter steps (EKF,
UKF, continuous-discrete EKF, quaternion filters, a gradient-descent attitude filter), emits them
as plain C99 (no heap, no globals), compiles them (:mod:`symkf.codegen`) and calls them from
Python over numpy buffers (:mod:`symkf.runtime`). :mod:`symkf.scenarios` holds four paper
reproductions and the ``symkf`` command line.

    from symkf.runtime import load
    tracker = load("tracker.py")                 # a file whose build() returns a Model; built if stale
    ekf = tracker.ekf(x0, P0, Q=Q)
    ekf.step(ekf.t, dt, z, "radar")              # predict from the filter time t to t + dt, update with z there

Sub-packages (import them; this package itself only carries the version and this text):

- ``symkf.models``: :class:`~symkf.models.Model` (states, inputs, parameters, noises,
  dynamics, measurements) and the four paper models;
- ``symkf.codegen``: Model -> CasADi Functions -> C, the cached build, codegen options
  (``symkf options`` lists them);
- ``symkf.runtime``: ``load``, ``CompiledModel``, ``Filter`` (predict, update, step, run) and the
  NumPy references;
- ``symkf.scenarios``: the paper experiments, Monte Carlo campaigns, the command line.

Documentation: the ``docs/`` folder of the source repository (``mkdocs serve`` there).
"""
from importlib.metadata import PackageNotFoundError, version as _version

try:
    __version__: str = _version("symkf")
except PackageNotFoundError:           # the sources imported without an install: no metadata to read
    __version__ = "0+unknown"

__all__ = ["__version__"]

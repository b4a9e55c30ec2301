"""Filter families beyond the generic EKF/UKF: one module each, registered on import.

A module here defines ``def kernels(model, symbols, functions) -> list[Kernel]`` and calls
``symkf.codegen.filters.register_family("<name>", kernels)``. Every module in this folder is
imported below, so adding a family is adding a file.
"""
import importlib
import pkgutil

for _module in pkgutil.iter_modules(__path__):
    importlib.import_module(f"{__name__}.{_module.name}")

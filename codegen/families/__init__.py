"""Filter families, one module per algorithm, each registered on import.

``kalman`` (EKF, UKF), ``cd_ekf`` (continuous-discrete EKF), ``manifold`` (multiplicative EKF and
manifold UKF for models with quaternion states), ``quaternion_filters`` (the noise-sampling
manifold UKFs of paper 000, separated and augmented, and the quaternion mean),
``gradient_descent`` (MARG filter). A module here defines
``def kernels(model, symbols, functions) -> Family`` (its kernels and the
:class:`~symkf.codegen.spec.FilterSpec` of every filter they make up) and calls
``symkf.codegen.kernels.register_family("<name>", kernels)``. Every module in this folder is
imported below, so adding a family is adding a file.
"""
import importlib
import pkgutil

for _module in pkgutil.iter_modules(__path__):
    importlib.import_module(f"{__name__}.{_module.name}")

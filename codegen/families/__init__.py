"""Filter families, one module per algorithm, each registered on import, and their framework.

``framework`` (the framework every family builds on; it registers none), ``kalman`` (EKF, UKF),
``cd_ekf`` (continuous-discrete EKF), ``chart`` (the manifold chart, its options and the quaternion
mean) and ``manifold`` (what the manifold filters share), ``mekf`` (multiplicative EKF), ``mukf``
(manifold UKF), ``quaternion_filters`` (the noise-sampling manifold UKFs of paper 000, separated and
augmented), ``gradient_descent`` (MARG filter). A family module defines
``def kernels(model, symbols, functions) -> Family`` (its kernels and the
:class:`~symkf.codegen.spec.FilterSpec` of every filter they make up) and calls
``framework.register_family("<name>", kernels, options=(...))`` with its typed options. Every
module in this folder is imported below, so adding a family is adding a file.
"""
import importlib
import pkgutil

for _module in pkgutil.iter_modules(__path__):
    importlib.import_module(f"{__name__}.{_module.name}")

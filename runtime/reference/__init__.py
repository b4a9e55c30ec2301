"""NumPy references of the generated filters: the readable oracles (and the "plain Python" timing
column). One module per family, each with the compiled filter's shape (``x``, ``P``,
``predict``/``update``/``step``):

- :mod:`.kalman`: :class:`ReferenceFilter`, the EKF and UKF of ``codegen/families/kalman.py``;
- :mod:`.cd_ekf`: :class:`NumpyCDEKF`, the continuous-discrete EKF;
- :mod:`.manifold`: :class:`ManifoldReference`, the multiplicative EKF and the manifold UKF;
- :mod:`.square_root`: :class:`SquareRootReference`, the square-root UKF and EKF (factor carried);
- :mod:`.square_root_cd_ekf`: :class:`NumpySquareRootCDEKF`, the square-root continuous-discrete EKF;
- :mod:`.square_root_manifold`: :class:`SquareRootManifoldReference`, the square-root MEKF;
- :mod:`.gradient_descent`: :class:`ReferenceGradientDescent`, the gradient-descent orientation filter.

:func:`for_family` finds the reference of a family by its name. The model is evaluated through
CasADi (the same Functions the C code calls); compiled and reference filters agree to round-off
on the same inputs (tests/test_contract.py).
"""
from __future__ import annotations

from .cd_ekf import NumpyCDEKF
from .common import wrap_angle
from .gradient_descent import ReferenceGradientDescent
from .kalman import ReferenceFilter
from .manifold import ManifoldReference
from .square_root import SquareRootReference
from .square_root_cd_ekf import NumpySquareRootCDEKF
from .square_root_manifold import SquareRootManifoldReference

#: The NumPy reference of each generated family.
REFERENCE_OF_FAMILY = {"ekf": ReferenceFilter, "ukf": ReferenceFilter, "cd_ekf": NumpyCDEKF,
                       "mekf": ManifoldReference, "mukf": ManifoldReference, "gradient_descent": ReferenceGradientDescent,
                       "srukf": SquareRootReference, "srekf": SquareRootReference,
                       "srmekf": SquareRootManifoldReference, "srcdekf": NumpySquareRootCDEKF}


def for_family(family: str):
    """The NumPy reference class of ``family`` (KeyError naming the families that have one)."""
    try:
        return REFERENCE_OF_FAMILY[family]
    except KeyError:
        raise KeyError(f"no NumPy reference for family {family!r}; references exist for "
                       f"{', '.join(sorted(REFERENCE_OF_FAMILY))}") from None


__all__ = ["ManifoldReference", "NumpyCDEKF", "NumpySquareRootCDEKF", "ReferenceFilter", "ReferenceGradientDescent", "SquareRootManifoldReference", "SquareRootReference", "for_family", "wrap_angle"]

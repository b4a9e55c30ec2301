"""The covariance a user gives and reads, and the factor a square-root filter's kernels carry.

A square-root family (``FilterSpec.covariance == "cholesky"``, codegen/families/srukf.py,
srekf.py) carries in its ``P`` buffer the lower Cholesky factor L of the covariance, P = L L^T.
:class:`CholeskyForm` converts at the boundary, in double: ``Filter.P`` gives and returns P as
for every filter; ``Filter.factor`` reads L. A positive semi-definite P (an exactly known state)
has a factor with a zero column (:func:`psd_factor`).
"""
from __future__ import annotations

import numpy as np

#: A pivot at or below this fraction of its diagonal entry is a zero pivot (a zero column of L).
ZERO_PIVOT = 1e-12


def psd_factor(P: np.ndarray) -> np.ndarray:
    """Lower L with L L^T = P for a symmetric positive semi-definite P (checked by the caller):
    Cholesky with a zero column where the pivot is zero (to ``ZERO_PIVOT``), diagonal >= 0."""
    P = np.asarray(P, dtype=float)
    n = P.shape[0]
    L = np.zeros((n, n))
    for j in range(n):
        pivot = P[j, j] - L[j, :j] @ L[j, :j]
        if pivot > ZERO_PIVOT * abs(P[j, j]) and pivot > 0:
            L[j, j] = np.sqrt(pivot)
            L[j + 1:, j] = (P[j + 1:, j] - L[j + 1:, :j] @ L[j, :j]) / L[j, j]
    return L


class CholeskyForm:
    """P = L L^T: the user's covariance to the kernels' factor and back (batches of factors too)."""

    @staticmethod
    def of(spec) -> "CholeskyForm | None":
        """The conversion of a filter whose kernels carry a factor, else None (they carry P)."""
        return CholeskyForm() if getattr(spec, "covariance", "full") == "cholesky" else None

    @staticmethod
    def to_kernel(P: np.ndarray) -> np.ndarray:
        return psd_factor(P)

    @staticmethod
    def from_kernel(L: np.ndarray) -> np.ndarray:
        """L L^T (for an array of factors, each one), lower triangle read."""
        L = np.tril(np.asarray(L, dtype=float))
        P = L @ np.swapaxes(L, -1, -2)
        return 0.5 * (P + np.swapaxes(P, -1, -2))

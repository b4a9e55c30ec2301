"""Square-root covariance algebra in CasADi SX: triangularisation (QR) and rank-one Cholesky
updates and downdates, unrolled into branch-free C like ``codegen/linalg.py``.

A covariance P is carried as its lower-triangular Cholesky factor L (P = L L^T, diagonal >= 0).
- :func:`triangularize`: the lower factor L of A A^T from A itself (Householder QR of A^T,
  Golub & Van Loan, Matrix Computations, alg. 5.2.1), without forming A A^T: the numbers
  squared never appear, so a factor spanning 1e-8 to 1e3 survives single precision.
- :func:`cholesky_update`: the factor of L L^T + sigma v v^T (sigma = +1: Givens rotations;
  sigma = -1: hyperbolic rotations, which fail, flag 0, if the result is not positive definite),
  Van der Merwe & Wan, "The square-root unscented Kalman filter for state and parameter
  estimation", ICASSP 2001, "cholupdate".
- :func:`cholesky_psd`: the factor of a positive *semi*-definite matrix (a zero pivot gives a
  zero column), for process noise densities with exact zeros.

Trap safety as in ``linalg``: every denominator is guarded where its branch is discarded.
"""
from __future__ import annotations

import casadi as ca

from . import linalg


def _sign(v: ca.SX) -> ca.SX:
    """+1 for v >= 0, else -1 (a Householder reflection's sign, chosen against cancellation)."""
    return ca.if_else(v >= 0, 1, -1)


def triangularize(A: ca.SX) -> ca.SX:
    """Lower-triangular L (n x n, diagonal >= 0) with L L^T = A A^T, for A of n rows and any
    number of columns: Householder QR of A^T = Q R, L = R^T with each column's sign made that
    of a non-negative diagonal. A column with nothing below its diagonal is not reflected, so a
    lower-triangular A (an all-masked update's pre-array) comes back exactly (up to signs)."""
    n, m = A.shape
    B = [[A[j, i] for j in range(n)] for i in range(m)]        # B = A^T, m x n, as entries
    if m < n:
        B += [[ca.SX(0)] * n for _ in range(n - m)]
        m = n
    diagonal = []
    for k in range(n):
        column = [B[i][k] for i in range(k, m)]
        below = sum((c * c for c in column[1:]), ca.SX(0))
        norm = ca.sqrt(column[0] * column[0] + below)
        alpha = -_sign(column[0]) * norm                       # R_kk = alpha
        u = [column[0] - alpha] + column[1:]
        uu = norm * (norm + ca.fabs(column[0]))                # u^T u / 2
        reflect = below > 0            # else the column is triangular already: kept exactly
        inv = 1 / linalg.guarded(uu, reflect)
        for j in range(k + 1, n):
            dot = sum((u[i - k] * B[i][j] for i in range(k, m)), ca.SX(0)) * inv
            for i in range(k, m):
                B[i][j] = linalg.select(reflect, B[i][j] - dot * u[i - k], B[i][j])
        diagonal.append(linalg.select(reflect, alpha, column[0]))
    L = ca.SX.zeros(n, n)
    for k in range(n):
        flip = ca.if_else(diagonal[k] < 0, -1, 1)              # column sign: diagonal >= 0
        L[k, k] = flip * diagonal[k]
        for i in range(k + 1, n):
            L[i, k] = flip * B[k][i]
    return L


def cholesky_update(L: ca.SX, v: ca.SX, sigma: int) -> tuple[ca.SX, ca.SX]:
    """The lower factor of L L^T + sigma v v^T (sigma = +1 or -1) and a 0/1 flag: 0 when a
    downdate leaves a matrix that is not positive definite (a zero component of v at a zero
    pivot changes nothing and is allowed). L's diagonal must be >= 0."""
    n = L.shape[0]
    L = ca.SX(L)
    v = [v[i] for i in range(n)]
    ok = ca.SX(1)
    for k in range(n):
        lkk, vk = L[k, k], v[k]
        if sigma > 0:                                          # Givens: [lkk, vk] -> [r, 0]
            r = ca.sqrt(lkk * lkk + vk * vk)
            rotate = r > 0
            c = linalg.select(rotate, lkk / linalg.guarded(r, rotate), 1)
            s = linalg.select(rotate, vk / linalg.guarded(r, rotate), 0)
            for i in range(k + 1, n):
                lik = L[i, k]
                L[i, k] = c * lik + s * v[i]
                v[i] = c * v[i] - s * lik
        else:                                                  # hyperbolic: r^2 = lkk^2 - vk^2
            d = lkk * lkk - vk * vk
            good = (d > 0) * (lkk > 0)
            trivial = vk == 0
            ok = ok * (good + (1 - good) * trivial)
            r = linalg.select(good, ca.sqrt(linalg.guarded(d, good)), lkk)
            safe = linalg.guarded(lkk, good)
            c = linalg.select(good, r / safe, 1)
            s = linalg.select(good, vk / safe, 0)
            for i in range(k + 1, n):
                L[i, k] = (L[i, k] - s * v[i]) / c
                v[i] = c * v[i] - s * L[i, k]
        L[k, k] = r
    return L, ok


def cholesky_psd(A: ca.SX) -> tuple[ca.SX, ca.SX]:
    """Lower L with L L^T = A for a symmetric positive semi-definite A (a pivot <= tol A_jj,
    e.g. an exact zero variance, gives a zero column), and a 0/1 flag that no pivot was negative
    beyond that tolerance (``linalg.PSD_TOLERANCE`` relative to the diagonal)."""
    n = A.shape[0]
    L = ca.SX.zeros(n, n)
    ok = ca.SX(1)
    for j in range(n):
        pivot = A[j, j] - sum((L[j, k] ** 2 for k in range(j)), ca.SX(0))
        tol = linalg.PSD_TOLERANCE * ca.fabs(A[j, j])
        ok = ok * (pivot >= -tol)
        positive = pivot > tol
        L[j, j] = linalg.select(positive, ca.sqrt(linalg.guarded(pivot, positive)), 0)
        inverse = linalg.select(positive, 1 / linalg.guarded(L[j, j], positive), 0)
        for i in range(j + 1, n):
            L[i, j] = (A[i, j] - sum((L[i, k] * L[j, k] for k in range(j)), ca.SX(0))) * inverse
    return L, ok


def factor_flag(L: ca.SX) -> ca.SX:
    """1 if every diagonal entry of the factor L is >= 0 (and finite), else 0."""
    ok = ca.SX(1)
    for i in range(L.shape[0]):
        ok = ok * (L[i, i] >= 0) * (L[i, i] < ca.inf)
    return ok


def outer_of(L: ca.SX) -> ca.SX:
    """L L^T, lower triangle computed once and mirrored (exactly symmetric)."""
    return linalg.symmetric(L.shape[0], lambda i, j: ca.dot(L[i, :].T, L[j, :].T))


def usable_factor(L: ca.SX) -> tuple[ca.SX, ca.SX]:
    """L with each diagonal entry that is not > 0 replaced by 1 (for triangular solves whose result
    is discarded then), and a 0/1 flag that every diagonal entry was > 0."""
    L = ca.SX(L)
    ok = ca.SX(1)
    for i in range(L.shape[0]):
        positive = L[i, i] > 0
        ok = ok * positive
        L[i, i] = linalg.guarded(L[i, i], positive)
    return L, ok

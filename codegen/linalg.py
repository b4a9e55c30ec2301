"""Small dense linear algebra written in CasADi SX, so it unrolls into branch-free C.

Cholesky factorisation reports failure as data (a flag) instead of producing NaN, and the kernels are
trap-safe: a branch-free kernel evaluates every branch, including the ones it then discards, so a
denominator is guarded (replaced by 1 where the branch will be discarded, :func:`guarded`), never
the result. A failed pivot is replaced by 1 before its square root divides the column below it.
"""
from __future__ import annotations

import casadi as ca

TINY = 1e-300


def symmetrize(A: ca.SX) -> ca.SX:
    return 0.5 * (A + A.T)


def symmetric(n: int, entry) -> ca.SX:
    """The n x n symmetric matrix whose lower triangle is ``entry(i, j)`` (i >= j), mirrored: the
    upper half is not computed (half the work of forming a full product and symmetrizing it)."""
    M = ca.SX.zeros(n, n)
    for j in range(n):
        for i in range(j, n):
            M[i, j] = entry(i, j)
            M[j, i] = M[i, j]
    return M


def sandwich(A: ca.SX, B: ca.SX) -> ca.SX:
    """A B A^T for a symmetric B, lower triangle computed once and mirrored (exactly symmetric)."""
    AB = A @ B
    return symmetric(A.shape[0], lambda i, j: ca.dot(AB[i, :].T, A[j, :].T))


def gram(U: ca.SX) -> ca.SX:
    """U^T U, lower triangle only, mirrored (bit-identical to the full product: U_ki U_kj = U_kj U_ki)."""
    return symmetric(U.shape[1], lambda i, j: ca.dot(U[:, i], U[:, j]))


def symmetric_part(A: ca.SX, i: int, j: int) -> ca.SX:
    """Entry (i, j) of 0.5 (A + A^T) (A itself on the diagonal)."""
    return A[i, i] if i == j else 0.5 * (A[i, j] + A[j, i])


def cholesky(A: ca.SX) -> tuple[ca.SX, ca.SX]:
    """Lower-triangular L with L L^T = A, and a 0/1 flag that A was positive definite."""
    n = A.shape[0]
    L = ca.SX.zeros(n, n)
    ok = ca.SX(1)
    for j in range(n):
        pivot = A[j, j] - sum((L[j, k] ** 2 for k in range(j)), ca.SX(0))
        usable = (pivot > 0) * (pivot < ca.inf)
        ok = ok * usable
        L[j, j] = ca.sqrt(ca.fmax(guarded(pivot, usable), TINY))
        for i in range(j + 1, n):
            L[i, j] = (A[i, j] - sum((L[i, k] * L[j, k] for k in range(j)), ca.SX(0))) / L[j, j]
    return L, ok


def solve_lower(L: ca.SX, B: ca.SX) -> ca.SX:
    """Solve L X = B by forward substitution (L lower triangular)."""
    n = L.shape[0]
    rows = []
    for i in range(n):
        acc = B[i, :]
        for k in range(i):
            acc = acc - L[i, k] * rows[k]
        rows.append(acc / L[i, i])
    return ca.vertcat(*rows)


def solve_upper_t(L: ca.SX, B: ca.SX) -> ca.SX:
    """Solve L^T X = B by back substitution (L lower triangular)."""
    n = L.shape[0]
    rows = [None] * n
    for i in reversed(range(n)):
        acc = B[i, :]
        for k in range(i + 1, n):
            acc = acc - L[k, i] * rows[k]
        rows[i] = acc / L[i, i]
    return ca.vertcat(*rows)


def cholesky_solve(L: ca.SX, B: ca.SX) -> ca.SX:
    """Solve A X = B given A's Cholesky factor L."""
    return solve_upper_t(L, solve_lower(L, B))


def wrap_angle(a: ca.SX) -> ca.SX:
    """Wrap to (-pi, pi]: a - 2 pi ceil((a - pi) / 2 pi) (exact multiples of 2 pi removed; cheaper
    than atan2(sin a, cos a), which costs three transcendental calls per wrapped component)."""
    return a - 2 * ca.pi * ca.ceil((a - ca.pi) / (2 * ca.pi))


def finite_flag(v: ca.SX) -> ca.SX:
    """1 if v is finite, else 0, without an ordered comparison on NaN (which raises FE_INVALID):
    NaN != NaN is tested first, and only a number is compared with infinity."""
    is_number = v == v
    return is_number * (ca.fabs(ca.if_else(is_number, v, 0)) < ca.inf)


def guarded(denominator: ca.SX, ok: ca.SX) -> ca.SX:
    """The denominator where ``ok``, else 1: for a division whose result is discarded when not
    ``ok`` (a branch-free kernel evaluates it anyway; it must not divide by zero or overflow)."""
    return ca.if_else(ok, denominator, 1)


def select(flag: ca.SX, if_true: ca.SX, if_false: ca.SX) -> ca.SX:
    """Element-wise if_else that never lets NaN in the unselected branch leak through."""
    return ca.if_else(flag, if_true, if_false)


#: Relative tolerance of :func:`psd_flag` (on the correlation matrix).
PSD_TOLERANCE = 1e-9


def psd_flag(A: ca.SX) -> ca.SX:
    """0/1 flag that the symmetric A is positive semi-definite: no negative (or NaN) variance and
    a Cholesky factorisation of its correlation matrix D^-1/2 A D^-1/2 + tol I succeeds.

    Computed as: the LDL^T pivots of A + tol diag(a) are all positive (a_i = A_ii, or 1 for a zero
    variance). The same test: that matrix is D^1/2 (C + tol I) D^1/2 with D = diag(a), and a
    congruence by a positive diagonal scales the j-th pivot by a_j, keeping its sign (no square
    roots, no fmax; one division per pivot)."""
    n = A.shape[0]
    ok, scale = ca.SX(1), []
    for i in range(n):
        ok = ok * (A[i, i] >= 0) * (A[i, i] < ca.inf)
        usable = (A[i, i] > 0) * (A[i, i] < ca.inf)      # else refused (or a zero variance: scale 1)
        scale.append(ca.if_else(usable, ca.if_else(A[i, i] > TINY, A[i, i], TINY), 1))
    L, LD, d = {}, {}, []                              # LD[i, k] = L[i, k] d[k]
    for j in range(n):
        pivot = A[j, j] + PSD_TOLERANCE * scale[j] - sum((LD[j, k] * L[j, k] for k in range(j)), ca.SX(0))
        usable = (pivot > 0) * (pivot < ca.inf)
        ok = ok * usable
        d.append(guarded(pivot, usable))
        inverse = 1 / d[j]
        for i in range(j + 1, n):
            LD[i, j] = A[i, j] - sum((LD[i, k] * L[j, k] for k in range(j)), ca.SX(0))
            L[i, j] = LD[i, j] * inverse
    return ok

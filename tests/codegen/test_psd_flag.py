"""linalg.psd_flag (LDLᵀ pivots of A + tol diag(a)) against its definition in NumPy: a Cholesky
factorisation of the correlation matrix D^-1/2 A D^-1/2 + tol I succeeds (zero variances scaled by 1)."""
import casadi as ca
import numpy as np

from symkf.codegen import linalg


def _definition(A: np.ndarray) -> float:
    d = np.diag(A)
    if np.any(d < 0) or not np.all(np.isfinite(d)):
        return 0.0
    scale = 1 / np.sqrt(np.where(d > 0, d, 1.0))
    try:
        np.linalg.cholesky(scale[:, None] * A * scale[None, :] + linalg.PSD_TOLERANCE * np.eye(len(d)))
    except np.linalg.LinAlgError:
        return 0.0
    return 1.0


def test_psd_flag_matches_its_definition():
    A = ca.SX.sym("A", 5, 5)
    flag = ca.Function("flag", [A], [linalg.psd_flag(A)])
    rng = np.random.default_rng(7)
    seen = set()
    for _ in range(3000):
        M = rng.normal(size=(5, 5)) * rng.choice([1e-4, 1.0, 1e4], 5)[:, None]
        w, V = np.linalg.eigh(M @ M.T)
        w[rng.integers(5)] = rng.choice([-1e-3, -1e-12, 0.0, 1e-12, 1e-3]) * w.max()
        S = V @ np.diag(w) @ V.T
        S = (S + S.T) / 2
        kind = rng.integers(4)
        if kind == 1:                                    # a state with zero variance: PSD
            i = rng.integers(5)
            S[i, :] = S[:, i] = 0.0
        elif kind == 2:                                  # a negative variance
            i = rng.integers(5)
            S[i, i] = -abs(S[i, i]) - 1e-9
        expected = _definition(S)
        seen.add(expected)
        assert float(flag(S)) == expected
    assert seen == {0.0, 1.0}

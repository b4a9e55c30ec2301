"""Issue 12: the UKF's weighted sums of sigma-point products in fewer operations, the same numbers.

``linalg.weighted_outer_sum`` forms sum_k w_k a_k a_k^T on its lower triangle (mirrored: exactly
symmetric) with the 2n equal weights applied once to their group's sum, where the kernels formed
the full product of every term and symmetrized it. Both are sums of the same products: they agree
to a few units of round-off, checked here against the former formula in NumPy."""
import casadi as ca
import numpy as np

from symkf.codegen import linalg
from symkf.codegen.c_writer import _inline_helpers


def _former(weights, A, B=None, R=None):
    """The kernels' formula before issue 12: sum_k (w_k a_k) b_k^T (+ R), symmetrized when B is A."""
    B = A if B is None else B
    total = sum(np.outer(w * a, b) for w, a, b in zip(weights, A, B))
    if R is not None or B is A:
        total = total + (0 if R is None else R)
        total = 0.5 * (total + total.T)
    return total


def _columns(rng, n, k, scale):
    return [rng.standard_normal(n) * scale for _ in range(k)]


def test_weighted_outer_sum_equals_the_former_products_and_is_exactly_symmetric():
    rng = np.random.default_rng(12)
    n, kappa = 6, 0.5
    w0, w = kappa / (n + kappa), 0.5 / (n + kappa)
    scale = np.array([0.03, 1e-5, 1e-5, 1.0, 1.6e-7, 1.6e-7])           # the launcher's 1-sigma spread
    for _ in range(20):
        A = _columns(rng, n, 2 * n + 1, scale)
        sym_w0, sym_w = ca.SX.sym("w0"), ca.SX.sym("w")
        cols = [ca.SX.sym(f"a{k}", n) for k in range(2 * n + 1)]
        expr = linalg.weighted_outer_sum([sym_w0] + [sym_w] * (2 * n), cols)
        value = np.array(ca.Function("f", [sym_w0, sym_w, *cols], [expr])(w0, w, *A))
        expected = _former([w0] + [w] * (2 * n), A)
        assert np.array_equal(value, value.T)
        d = np.sqrt(np.diag(expected))
        assert np.max(np.abs(value - expected) / np.outer(d, d)) < 1e-14


def test_weighted_cross_sum_equals_the_former_products():
    rng = np.random.default_rng(5)
    weights = [0.2] + [0.4] * 4
    A, B = _columns(rng, 6, 5, 1.0), _columns(rng, 3, 5, 10.0)
    cols_a = [ca.SX.sym(f"a{k}", 6) for k in range(5)]
    cols_b = [ca.SX.sym(f"b{k}", 3) for k in range(5)]
    sym_w = [ca.SX.sym("w0")] + [ca.SX.sym("w")] * 4
    expr = linalg.weighted_outer_sum(sym_w, cols_a, cols_b)
    value = np.array(ca.Function("f", [sym_w[0], sym_w[1], *cols_a, *cols_b], [expr])(0.2, 0.4, *A, *B))
    assert value.shape == (6, 3)
    expected = sum(np.outer(w * a, b) for w, a, b in zip(weights, A, B))
    assert np.allclose(value, expected, rtol=1e-14, atol=1e-14 * np.abs(expected).max())


def test_weighted_sum_groups_only_identical_weights():
    a, b, c = ca.SX.sym("a"), ca.SX.sym("b"), ca.SX.sym("c")
    w1, w2 = ca.SX.sym("w1"), ca.SX.sym("w2")
    f = ca.Function("f", [w1, w2, a, b, c], [linalg.weighted_sum([w1, w2, w2], [a, b, c]),
                                               linalg.weighted_sum([w1, w2, w2], [a, b, c], group=False)])
    grouped, plain = f(2.0, 3.0, 1.0, 10.0, 100.0)
    assert float(grouped) == 2.0 + 3.0 * 110.0 and float(plain) == 2.0 + 30.0 + 300.0
    assert f.n_instructions() < 20


def test_casadi_helpers_are_static_inline():
    code = ("static casadi_real casadi_sq(casadi_real x) { return x*x;}\n"
            "static void casadi_copy(const casadi_real* x, casadi_int n, casadi_real* y) {\n"
            "static casadi_real casadi_dot(casadi_int n, const casadi_real* x, const casadi_real* y) {\n")
    out = _inline_helpers(code)
    assert "static inline casadi_real casadi_sq(" in out and "static inline void casadi_copy(" in out
    assert "static casadi_real casadi_dot(" in out                 # other helpers as CasADi wrote them


def test_launcher_ukf_units_call_no_helper(launcher_compiled):
    """The generated units inline casadi_sq (138 calls per UKF prediction before issue 12)."""
    directory = launcher_compiled.build.directory
    text = (directory / "launcher_fn_fd_sigma_plain.c").read_text()
    assert "static inline casadi_real casadi_sq(" in text

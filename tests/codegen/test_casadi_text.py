"""CasADi's small helpers inline in the generated units (bit-identical, fewer calls).

The UKF's weighted sums of sigma-point products stay as they were, term by term and symmetrized:
grouping the equal weights or one triangle moved P by round-off, which the campaign's excursion
runs amplified into Table 3 (see codegen/families/kalman.py, _sigma_covariance)."""
from symkf.codegen.c_backend.casadi_text import _inline_helpers


def test_casadi_helpers_are_static_inline():
    code = ("static casadi_real casadi_sq(casadi_real x) { return x*x;}\n"
            "static void casadi_copy(const casadi_real* x, casadi_int n, casadi_real* y) {\n"
            "static casadi_real casadi_dot(casadi_int n, const casadi_real* x, const casadi_real* y) {\n")
    out = _inline_helpers(code)
    assert "static inline casadi_real casadi_sq(" in out and "static inline void casadi_copy(" in out
    assert "static casadi_real casadi_dot(" in out                 # other helpers as CasADi wrote them


def test_launcher_ukf_units_call_no_helper(launcher_compiled):
    """The generated units inline casadi_sq (there were 138 calls per UKF prediction)."""
    directory = launcher_compiled.build.directory
    text = (directory / "launcher_fn_fd_sigma_plain.c").read_text()
    assert "static inline casadi_real casadi_sq(" in text

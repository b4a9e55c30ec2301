"""Square-root continuous-discrete EKF, family ``"srcdekf"``: the continuous-discrete EKF of
``cd_ekf.py`` (paper 003 Table 1, Lewis 1986) carrying the lower Cholesky factor L of P (P = L L^T).

**Time update, and why this form.** The CD-EKF integrates the Riccati ODE
P' = A P + P A^T + Q together with x' = a(x). Integrating it *in factored form* (an ODE for L,
e.g. L' = (A + M) L with M from Q and L^-1) needs L^-1 at every stage: it fails for a singular
factor and is stiff where P spans many decades, the cases a square root is for. The standard
practical choice (Grewal & Andrews, Kalman Filtering, 4th ed. 2015, sec. 6.6; Kailath, Sayed &
Hassibi, Linear Estimation, 2000, sec. 12.3) is taken instead: per RK4 sub-step h
(``CodegenConfig.rk4_substeps``), integrate with the same RK4 stages as the CD-EKF

    x' = a(x),   Phi' = A(x) Phi (Phi(0) = I),   Q_d' = A(x) Q_d + Q_d A(x)^T + Q (Q_d(0) = 0),

(A = da/dx, sparse, at the stage states), so that the CD-EKF's P(h) = Phi P Phi^T + Q_d to the
order of the integrator (RK4 of the Riccati and Phi P Phi^T + Q_d differ by O(h^5) per sub-step),
then re-factor by a QR of the pre-array: L+ = qr[Phi L, chol(Q_d)]. P itself is never formed;
only Q_d (the noise of one sub-step, no product of L with itself) is, and factored by
``square_root.cholesky_psd`` (a zero variance gives a zero column). A Q_d that is not positive
semi-definite (to its tolerance) is SYMKF_ERR_NOT_PD, x and L unchanged.

**Update.** The discrete update of the square-root EKF (``srekf.srekf_update_expr``): the pre-array
[[chol(R), H L], [0, L]] triangularised to [[S^1/2, 0], [K_b, L+]], x+ = x + K_b S^-1/2 y, the
CD-EKF's P - K U in exact arithmetic. Masks, gates and status codes are those of ``framework.py``;
the carried factor as in ``srukf.py`` (lower triangle read, written with 0 above the diagonal and a
diagonal >= 0); Q as the CD-EKF's: the n x n power spectral density of an additive noise on every state.

Kernels: ``srcdekf_predict``, ``srcdekf_update_<meas>``, ``srcdekf_step_<meas>`` (predict + update).
"""
from __future__ import annotations

import casadi as ca

from symkf.models.base import Model
from .. import square_root
from ..discretize import CALLED_OPTIONS, continuous_dynamics
from ..model_functions import ModelFunctions, Symbols
from ..spec import Family
from .cd_ekf import from_upper_triangle, upper_triangle
from .framework import filter_spec, make_kernel, register_family
from .kalman import predict_status
from .srekf import array_update_kernels
from .srukf import factor_arg

FAMILY = "srcdekf"


def transition_derivative(model: Model) -> ca.Function:
    """(t, x, Phi, Qtri, u, p, Q) -> (a(x), A Phi, triu(A Q_d + Q_d A^T + Q)), A = da/dx sparse."""
    n = model.nx
    f = continuous_dynamics(model)
    t, x, u, p = ca.SX.sym("t"), ca.SX.sym("x", n), ca.SX.sym("u", model.u.shape[0]), ca.SX.sym("p", model.p.shape[0])
    Phi, qtri, Q = ca.SX.sym("Phi", n, n), ca.SX.sym("Qtri", n * (n + 1) // 2), ca.SX.sym("Q", n, n)
    xdot = f(t, x, u, p, ca.DM.zeros(model.w.shape[0]))
    A = ca.jacobian(xdot, x)                       # sparse: only structural non-zeros multiply
    AQ = A @ from_upper_triangle(qtri, n)
    return ca.Function(f"{model.name}_srcd_derivative", [t, x, Phi, qtri, u, p, Q],
                       [xdot, A @ Phi, upper_triangle(AQ + AQ.T + Q)],
                       ["t", "x", "Phi", "Qtri", "u", "p", "Q"], ["xdot", "Phi_dot", "Qtri_dot"], CALLED_OPTIONS)


def transition_step(derivative: ca.Function, t, h, x, u, p, Q):
    """One RK4 sub-step of (x, Phi, Q_d) from (x, I, 0) over h (inputs held): x(h), Phi, Q_d."""
    n = x.shape[0]
    state = (x, ca.SX.eye(n), ca.SX.zeros(n * (n + 1) // 2))

    def rate(time, values):
        return derivative(time, *values, u, p, Q)

    def moved(values, slopes, scale):
        return tuple(v + scale * k for v, k in zip(values, slopes))

    k1 = rate(t, state)
    k2 = rate(t + h / 2, moved(state, k1, h / 2))
    k3 = rate(t + h / 2, moved(state, k2, h / 2))
    k4 = rate(t + h, moved(state, k3, h))
    x_next, Phi, qtri = (v + h / 6 * (a + 2 * b + 2 * c + d) for v, a, b, c, d in zip(state, k1, k2, k3, k4))
    return x_next, Phi, from_upper_triangle(qtri, n)


def srcdekf_predict_expr(model: Model, symbols: Symbols, substeps: int, L):
    """x and L at t + dt: per sub-step x, Phi, Q_d by RK4, L = qr[Phi L, chol(Q_d)]; a 0/1 flag
    (every Q_d PSD, L a factor)."""
    if substeps < 1:
        raise ValueError(f"{FAMILY}: rk4_substeps must be >= 1, got {substeps}")
    s = symbols.sym
    derivative = transition_derivative(model)
    x, h, ok = s["x"], s["dt"] / substeps, square_root.factor_flag(L)
    for i in range(substeps):
        x, Phi, Qd = transition_step(derivative, s["t"] + i * h, h, x, s["u"], s["p"], s["Q"])
        root, ok_q = square_root.cholesky_psd(Qd)
        L = square_root.triangularize(ca.horzcat(Phi @ L, root))
        ok = ok * ok_q
    return x, L, ok


def srcdekf_kernels(model: Model, symbols: Symbols, fns: ModelFunctions) -> Family:
    s = symbols.sym
    substeps = fns.config.rk4_substeps
    L = ca.tril(s["P"])                          # only the lower triangle is read
    factor = {"P": factor_arg(model.nx)}
    x_pred, L_pred, ok = srcdekf_predict_expr(model, symbols, substeps, L)
    kernels = [make_kernel(f"{FAMILY}_predict", "Square-root continuous-discrete EKF time update t -> t + dt: "
                           "x' = a(x), Phi' = A Phi, Q_d' = A Q_d + Q_d A^T + Q by RK4 "
                           f"({substeps} sub-step(s)), L = qr[Phi L, chol(Q_d)] per sub-step.",
                           symbols, {}, factor, ["t", "dt", "x", "P", "u", "p", "Q"],
                           [("x", x_pred), ("P", L_pred), ("status", predict_status(ok))])]
    kernels += array_update_kernels(FAMILY, "Square-root continuous-discrete EKF", model, symbols, fns, kernels[0])
    return Family(kernels, [filter_spec(FAMILY, FAMILY, kernels, model.measurements, covariance="cholesky")])


register_family(FAMILY, srcdekf_kernels)

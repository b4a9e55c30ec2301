"""Continuous-discrete EKF ("cd_ekf"), paper 003 Table 1 (Lewis 1986), for any model.

Time update: the estimate and the covariance are integrated *together* over [t, t + dt],

    xhat' = a(xhat, u, t),     P' = A(xhat) P + P A(xhat)^T + G Q G^T,   A = da/dx,

with RK4 (``CodegenConfig.rk4_substeps`` sub-steps, inputs held: zero-order hold).
G = I: ``Q`` is the n x n power spectral density of an additive noise on every state. A is
derived by CasADi and kept *sparse*: A P costs nnz(A) n multiplications, not n^3. Only the
upper triangle of P (n(n+1)/2 numbers) is integrated, since P' is symmetric by construction.

Measurement update (discrete, at each sensor's own rate): with U = H P (H sparse, masked rows 0),

    S = U H^T + R,  K = U^T S^-1,  P+ = P - K U  (= (I - K H) P of Table 1),
    xhat+ = xhat + K (z - h(xhat)).

P+ = P - K U costs O(n^2 m) instead of the O(n^3) of (I - K H) P, and is symmetrised. Masks as
in :mod:`symkf.codegen.families.framework`: a masked component contributes exactly nothing, all masked
leaves x and P bit-for-bit unchanged (K = 0). A non-PD S returns NOT_PD (and writes nothing).

C size and compile time: the augmented derivative (x', P') is one never-inlined SX function
(sparse A P unrolled, the only place where unrolling pays), called by a never-inlined RK4 step
written in MX, whose vector algebra becomes C loops. The updates are MX too: the small parts
(h, sparse H, masked R, innovation, the m x m Cholesky gain) are never-inlined SX functions and
the n x n algebra (H P, K U) is CasADi's sparse matrix-product loop. So the generated C grows with
nnz(A) n, not with n^3, the number of sub-steps or the number of sensors times n^2.

Fixed-interval smoothing (Rauch, Tung & Striebel 1965, the step of codegen/families/rts.py): the
backward step from k + 1 to k repeats row k's time update over step k + 1 with the forward pass's
own derivative function, RK4 and sub-steps, and integrates the state-transition matrix beside it,

    Phi' = A(xhat(t)) Phi,  Phi(t) = I   (so Phi = d xhat^- / d xhat(t) of the RK4 step, to its order),

then G = P Phi^T (P^-)^-1 by Cholesky, x^s = x + G (x^s_{k+1} - x^-), P^s = P + G (P^s_{k+1} - P^-) G^T.
Its n x n algebra is MX (C loops) like the update's; P^- without a Cholesky factor, or P or P^s
not PSD, is SYMKF_ERR_NOT_PD.

Kernels: ``cd_ekf_predict``, ``cd_ekf_update_<meas>``, ``cd_ekf_step_<meas>`` (predict + update),
``cd_ekf_smooth`` (the smoother's backward step; its C loop is ``<model>_cd_ekf_smooth_run``).
"""
from __future__ import annotations

import casadi as ca

from symkf.models.base import Model
from .. import linalg
from ..discretize import CALLED_OPTIONS, continuous_dynamics
from ..model_functions import ModelFunctions, Symbols
from ..spec import STATUS_NOT_PD, Family, Kernel
from .rts import PER_STEP, SMOOTHED, smoothed_symbols
from .framework import (all_finite, compose_step, filter_spec, gated, innovation, masked_finite, masked_noise,
                        register_family, update_status)

FAMILY = "cd_ekf"


def upper_triangle(P: ca.SX) -> ca.SX:
    """The n(n+1)/2 upper-triangle entries of P, column by column."""
    n = P.shape[0]
    return ca.vertcat(*[P[i, j] for j in range(n) for i in range(j + 1)])


def from_upper_triangle(v: ca.SX, n: int) -> ca.SX:
    """The symmetric matrix whose upper triangle (column by column) is v."""
    P = ca.SX(n, n)
    k = 0
    for j in range(n):
        for i in range(j + 1):
            P[i, j] = v[k]
            P[j, i] = v[k]
            k += 1
    return P


def augmented_derivative(model: Model) -> ca.Function:
    """(t, x, Ptri, u, p, Q) -> (a(x), triu(A P + P A^T + Q)) with A = da/dx sparse."""
    n = model.nx
    f = continuous_dynamics(model)
    t, x, u, p = ca.SX.sym("t"), ca.SX.sym("x", n), ca.SX.sym("u", model.u.shape[0]), ca.SX.sym("p", model.p.shape[0])
    ptri, Q = ca.SX.sym("Ptri", n * (n + 1) // 2), ca.SX.sym("Q", n, n)
    xdot = f(t, x, u, p, ca.DM.zeros(model.w.shape[0]))
    A = ca.jacobian(xdot, x)                       # sparse: only structural non-zeros multiply
    AP = A @ from_upper_triangle(ptri, n)
    pdot = upper_triangle(AP + AP.T + Q)
    return ca.Function(f"{model.name}_cd_derivative", [t, x, ptri, u, p, Q], [xdot, pdot],
                       ["t", "x", "Ptri", "u", "p", "Q"], ["xdot", "Ptri_dot"], CALLED_OPTIONS)


def rk4_step(model: Model, derivative: ca.Function) -> ca.Function:
    """One RK4 step of the augmented system (x, triu P) over h (inputs held)."""
    n = model.nx
    return rk4_of(model, derivative, f"{model.name}_cd_rk4", [("x", n, 1), ("Ptri", n * (n + 1) // 2, 1)])


def rk4_of(model: Model, derivative: ca.Function, name: str, states: list[tuple[str, int, int]]) -> ca.Function:
    """One RK4 step over h of the states ``(name, rows, columns)`` whose derivative is
    ``derivative(t, *states, u, p, Q)`` (inputs held), as a never-inlined MX function."""
    sym = ca.MX.sym                     # MX: the vector algebra becomes C loops, not unrolled lines
    t, h = sym("t"), sym("h")
    y = [sym(label, rows, cols) for label, rows, cols in states]
    u, p, Q = sym("u", model.u.shape[0]), sym("p", model.p.shape[0]), sym("Q", model.nx, model.nx)

    def slope(time, values):
        out = derivative(time, *values, u, p, Q)
        return list(out) if isinstance(out, (list, tuple)) else [out]
    k1 = slope(t, y)
    k2 = slope(t + h / 2, [a + h / 2 * b for a, b in zip(y, k1)])
    k3 = slope(t + h / 2, [a + h / 2 * b for a, b in zip(y, k2)])
    k4 = slope(t + h, [a + h * b for a, b in zip(y, k3)])
    y_next = [a + h / 6 * (b1 + 2 * b2 + 2 * b3 + b4) for a, b1, b2, b3, b4 in zip(y, k1, k2, k3, k4)]
    labels = [label for label, _, _ in states]
    return ca.Function(name, [t, h, *y, u, p, Q], y_next, ["t", "h", *labels, "u", "p", "Q"], labels,
                       {"allow_duplicate_io_names": True, "never_inline": True})


def triangle_indices(n: int) -> tuple[list[int], list[int]]:
    """Column-major positions of P's upper triangle, and for each of P's n^2 entries the
    position of its upper-triangle twin (so the full P is a gather, not n^2 assignments)."""
    upper = [i + j * n for j in range(n) for i in range(j + 1)]
    where = {(i, j): k for k, (i, j) in enumerate((i, j) for j in range(n) for i in range(j + 1))}
    full = [where[(min(i, j), max(i, j))] for j in range(n) for i in range(n)]
    return upper, full


def predict_function(model: Model, substeps: int) -> ca.Function:
    """x and P at t + dt from x, P at t (Table 1 time update), as an MX function."""
    if substeps < 1:
        raise ValueError(f"{FAMILY}: rk4_substeps must be >= 1, got {substeps}")
    n, sym = model.nx, ca.MX.sym
    t, dt, x0, P = sym("t"), sym("dt"), sym("x", n), sym("P", n, n)
    u, p, Q = sym("u", model.u.shape[0]), sym("p", model.p.shape[0]), sym("Q", n, n)
    step = rk4_step(model, augmented_derivative(model))
    upper, full = triangle_indices(n)
    h = dt / substeps
    x, ptri = x0, ca.vec(P)[upper]              # P is symmetric: its upper triangle is all of it
    for i in range(substeps):
        x, ptri = step(t + i * h, h, x, ptri, u, p, Q)
    names = ["t", "dt", "x", "P", "u", "p", "Q"]
    return ca.Function(f"{model.name}_k_{FAMILY}_predict", [t, dt, x0, P, u, p, Q],
                       [x, ca.reshape(ptri[full], n, n), ca.MX(0)], names, ["x", "P", "status"],
                       {"allow_duplicate_io_names": True})


# ---------------------------------------------------------------------- RTS smoother
def transition_derivative(model: Model):
    """(t, x, Ptri, Phi, u, p, Q) -> (a(x), triu(A P + P A^T + Q), A Phi): the forward pass's own
    :func:`augmented_derivative` (the same C function, so x^- and P^- are the forward's) and the
    transition matrix's dPhi/dt = A(x(t)) Phi, an SX function of its own (A sparse)."""
    n = model.nx
    f = continuous_dynamics(model)
    t, x, u, p = ca.SX.sym("t"), ca.SX.sym("x", n), ca.SX.sym("u", model.u.shape[0]), ca.SX.sym("p", model.p.shape[0])
    Phi = ca.SX.sym("Phi", n, n)
    A = ca.jacobian(f(t, x, u, p, ca.DM.zeros(model.w.shape[0])), x)
    phi_dot = ca.Function(f"{model.name}_cd_transition_derivative", [t, x, Phi, u, p], [A @ Phi],
                          ["t", "x", "Phi", "u", "p"], ["Phi_dot"], CALLED_OPTIONS)
    derivative = augmented_derivative(model)

    def slope(t, x, ptri, Phi, u, p, Q):
        return [*derivative(t, x, ptri, u, p, Q), phi_dot(t, x, Phi, u, p)]
    return slope


def transition_function(model: Model, substeps: int):
    """(t, dt, x, P, u, p, Q) -> x^-, P^- (the forward time update: same RK4, same sub-steps) and
    Phi = d x^- / d x(t) integrated alongside them from Phi(t) = I, as MX expressions."""
    n, sym = model.nx, ca.MX.sym
    args = {"t": sym("t"), "dt": sym("dt"), "x": sym("x", n), "P": sym("P", n, n), "u": sym("u", model.u.shape[0]),
            "p": sym("p", model.p.shape[0]), "Q": sym("Q", n, n)}
    step = rk4_of(model, transition_derivative(model), f"{model.name}_cd_rk4_transition",
                  [("x", n, 1), ("Ptri", n * (n + 1) // 2, 1), ("Phi", n, n)])
    upper, full = triangle_indices(n)
    h = args["dt"] / substeps
    x, ptri, Phi = args["x"], ca.vec(args["P"])[upper], ca.MX.eye(n)
    for i in range(substeps):
        x, ptri, Phi = step(args["t"] + i * h, h, x, ptri, Phi, args["u"], args["p"], args["Q"])
    return args, x, ca.reshape(ptri[full], n, n), Phi


def backward_function(n: int, prefix: str, psd: ca.Function):
    """(x, P, xs, Ps, x^-, P^-, Phi) -> x^s_k, P^s_k, status: the RTS step of codegen/families/rts.py
    with D = P Phi^T, written in MX like this family's update (the n x n products become C loops,
    not n^3 unrolled lines): G^T = (P^-)^-1 Phi P by Cholesky of P^- (an SX function) and one
    SX triangular solve mapped over the n columns; P^s_k = P_k + G (P^s_{k+1} - P^-) G^T, symmetrised.
    Status NOT_PD unless P_k and P^s_k are PSD (``psd``) and P^- is positive definite."""
    A, b = ca.SX.sym("A", n, n), ca.SX.sym("b", n)
    L, ok = linalg.cholesky(A)
    factor = ca.Function(f"{prefix}_cd_cholesky_{n}", [A], [L, ok], ["A"], ["L", "ok"], CALLED_OPTIONS)
    Ls = ca.SX.sym("L", n, n)
    solve = ca.Function(f"{prefix}_cd_cholesky_solve_{n}", [Ls, b], [linalg.cholesky_solve(Ls, b)], ["L", "b"], ["x"],
                        CALLED_OPTIONS).map(n, "serial")
    names = ["x", "P", "xs", "Ps", "x_pred", "P_pred", "Phi"]
    x, P, xs, Ps, x_pred, P_pred, Phi = (ca.MX.sym(name, n, 1 if name.startswith("x") else n) for name in names)
    L, ok_pred = factor(P_pred)
    Gt = solve(L, ca.mtimes(Phi, P))                     # G^T = (P^-)^-1 D^T, D^T = Phi P (P symmetric)
    change = ca.mtimes(ca.mtimes(Gt.T, Ps - P_pred), Gt)
    P_out = 0.5 * (P + P.T) + 0.5 * (change + change.T)
    status = ca.if_else(ok_pred * psd(P) * psd(P_out), 0, STATUS_NOT_PD)
    return ca.Function(f"{prefix}_cd_backward_{n}", [x, P, xs, Ps, x_pred, P_pred, Phi],
                       [x + ca.mtimes(Gt.T, xs - x_pred), P_out, status],
                       names, ["xs", "Ps", "status"], {"allow_duplicate_io_names": True, "never_inline": True})


def smooth_kernel(model: Model, symbols: Symbols, substeps: int) -> Kernel:
    """The continuous-discrete RTS backward step from step k + 1 to k: the time update of row k
    over step k + 1 recomputed with its transition matrix Phi, then G = P Phi^T (P^-)^-1."""
    args, x_pred, P_pred, Phi = transition_function(model, substeps)
    n = model.nx
    smoothed_sym, smoothed_arg = smoothed_symbols(symbols, ca.SX(n, n), symbols.arg["P"].unit)
    xs, Ps = ca.MX.sym("xs", n), ca.MX.sym("Ps", n, n)
    out = backward_function(n, model.name, covariance_check(n, model.name))(args["x"], args["P"], xs, Ps, x_pred, P_pred, Phi)
    names = list(args) + list(SMOOTHED)
    function = ca.Function(f"{model.name}_k_{FAMILY}_smooth", [*args.values(), xs, Ps], list(out), names,
                           ["xs", "Ps", "status"], {"allow_duplicate_io_names": True})
    inputs = tuple(symbols.arg[a] for a in args) + tuple(smoothed_arg[a] for a in SMOOTHED)
    return Kernel(f"{FAMILY}_smooth", function,
                  "Continuous-discrete EKF RTS smoother: one backward step from step k + 1 to k (x-, P- and "
                  f"Phi = dx-/dx by RK4, {substeps} sub-step(s); G = P Phi^T (P-)^-1).",
                  inputs, (smoothed_arg["xs"], smoothed_arg["Ps"], symbols.arg["status"]),
                  per_step=tuple(a for a in args if a in PER_STEP), backward=SMOOTHED)


def measurement_jacobian(model: Model, name: str) -> ca.Function:
    """h and its sparse Jacobian H = dh/dx of one measurement (inlined into the update)."""
    meas = model.measurements[name]
    args = [model.t, model.x, model.u, model.p, meas.q]
    return ca.Function(f"h_and_H_{name}", args, [meas.h, ca.jacobian(meas.h, model.x)],
                       ["t", "x", "u", "p", "q"], ["z", "H"])


def measurement_terms(model: Model, name: str) -> ca.Function:
    """(t, x, u, p, q, z, mask, R, gate) -> masked sparse H, masked R, innovation y, and a 0/1 flag
    that every input is finite (z only where used) (small, SX)."""
    meas = model.measurements[name]
    m, n = meas.size, model.nx
    t, x, u, p = ca.SX.sym("t"), ca.SX.sym("x", n), ca.SX.sym("u", model.u.shape[0]), ca.SX.sym("p", model.p.shape[0])
    q, z, mask, R = ca.SX.sym("q", meas.q.shape[0]), ca.SX.sym("z", m), ca.SX.sym("mask", m), ca.SX.sym("R", m, m)
    gate = ca.SX.sym("gate", m)
    z_pred, H = measurement_jacobian(model, name)(t, x, u, p, q)
    y = innovation(z, z_pred, mask, meas.wrap)
    finite = all_finite([t, x, u, p, q, mask, R, gate]) * masked_finite(z, mask)
    return ca.Function(f"{model.name}_cd_terms_{name}", [t, x, u, p, q, z, mask, R, gate],
                       [ca.diag(mask) @ H, masked_noise(R, mask), y, finite],
                       ["t", "x", "u", "p", "q", "z", "mask", "R", "gate"], ["H", "R", "y", "finite"], CALLED_OPTIONS)


def covariance_check(n: int, prefix: str) -> ca.Function:
    """P -> 0/1 flag that P is positive semi-definite (the EKF refuses anything else)."""
    P = ca.SX.sym("P", n, n)
    return ca.Function(f"{prefix}_cd_psd_{n}", [P], [linalg.psd_flag(P)], ["P"], ["ok"], CALLED_OPTIONS)


def kalman_gain(n: int, m: int, prefix: str) -> ca.Function:
    """(S, U, y) -> K = U^T S^-1 by Cholesky, a 0/1 flag that S was positive definite, and the
    normalised innovation squared y^T S^-1 y (for the gate)."""
    S, U, y = ca.SX.sym("S", m, m), ca.SX.sym("U", m, n), ca.SX.sym("y", m)
    L, ok = linalg.cholesky(linalg.symmetrize(S))
    return ca.Function(f"{prefix}_cd_gain_{n}x{m}", [S, U, y],
                       [linalg.cholesky_solve(L, U).T, ok, ca.sumsqr(linalg.solve_lower(L, y))],
                       ["S", "U", "y"], ["K", "ok", "nis"], CALLED_OPTIONS)


def update_function(model: Model, name: str, gain: ca.Function, psd: ca.Function) -> ca.Function:
    """Table 1 measurement update, masked (see module docstring), as an MX function: the
    n x n algebra (U = H P with H sparse, P - K U) is emitted as C loops, not unrolled."""
    meas = model.measurements[name]
    n, m = model.nx, meas.size
    sym = ca.MX.sym
    t, x, P, u, p = sym("t"), sym("x", n), sym("P", n, n), sym("u", model.u.shape[0]), sym("p", model.p.shape[0])
    q, z, mask, R, gate = sym("q", meas.q.shape[0]), sym("z", m), sym("mask", m), sym("R", m, m), sym("gate", m)
    H, R_masked, y, finite = measurement_terms(model, name)(t, x, u, p, q, z, mask, R, gate)
    U = ca.mtimes(H, P)                                   # m x n, only H's non-zeros multiply
    S = ca.mtimes(U, H.T) + R_masked
    S = 0.5 * (S + S.T)
    K, ok, nis = gain(S, U, y)                            # n x m = P H^T S^-1 (shared per m)
    P_new = P - ca.mtimes(K, U)                           # (I - K H) P
    P_new = 0.5 * (P_new + P_new.T)
    finite = finite * (ca.sum1(ca.sum2(ca.fabs(P) < ca.inf)) == n * n)
    ok = ok * psd(P)                                      # the EKF refuses a P with a negative variance
    is_gated = gated(gate, mask, nis)
    status = update_status(ok, is_gated, finite)
    keep = status == 0
    names = ["t", "x", "P", "u", "p", "q", "z", "mask", "R", "gate"]
    return ca.Function(f"{model.name}_k_{FAMILY}_update_{name}", [t, x, P, u, p, q, z, mask, R, gate],
                       [ca.if_else(keep, x + ca.mtimes(K, y), x), ca.if_else(keep, P_new, P), y, S, status],
                       names, ["x", "P", "y", "S", "status"], {"allow_duplicate_io_names": True})


def cd_ekf_kernels(model: Model, symbols: Symbols, functions: ModelFunctions) -> Family:
    """The continuous-discrete EKF of Table 1 for ``model`` (any model: nothing here is GEO-specific)."""
    substeps = functions.config.rk4_substeps
    predict = Kernel(f"{FAMILY}_predict", predict_function(model, substeps),
                     "Continuous-discrete EKF time update t -> t + dt: x' = a(x), P' = A P + P A^T + Q "
                     f"integrated together (RK4, {substeps} sub-step(s)).",
                     tuple(symbols.arg[a] for a in ("t", "dt", "x", "P", "u", "p", "Q")),
                     tuple(symbols.arg[a] for a in ("x", "P", "status")))
    gains = {m: kalman_gain(model.nx, m, model.name) for m in {meas.size for meas in model.measurements.values()}}
    psd = covariance_check(model.nx, model.name)
    kernels = [predict]
    for name in model.measurements:
        _, marg = symbols.measurement(name)
        args = {**symbols.arg, **marg}
        update = Kernel(f"{FAMILY}_update_{name}",
                        update_function(model, name, gains[model.measurements[name].size], psd),
                        f"Continuous-discrete EKF update with '{name}' at time t (masked, P = (I - K H) P).",
                        tuple(args[a] for a in ("t", "x", "P", "u", "p", "q", "z", "mask", "R", "gate")),
                        tuple(args[a] for a in ("x", "P", "y", "S", "status")))
        kernels += [update, compose_step(f"{FAMILY}_step_{name}", predict, update)]
    kernels.append(smooth_kernel(model, symbols, substeps))
    return Family(kernels, [filter_spec(FAMILY, FAMILY, kernels, model.measurements, smooth=f"{FAMILY}_smooth")])


register_family(FAMILY, cd_ekf_kernels)


def reference_functions(model: Model) -> dict[str, ca.Function]:
    """Numeric CasADi Functions for a NumPy reference of this family: a(x), dense A = da/dx, and
    per measurement h and dense H (the same symbolic sources as the generated kernels)."""
    f = continuous_dynamics(model)
    xdot = f(model.t, model.x, model.u, model.p, ca.DM.zeros(model.w.shape[0]))
    names = ["t", "x", "u", "p"]
    functions = {"a": ca.Function("a", [model.t, model.x, model.u, model.p], [xdot], names, ["xdot"]),
                 "A": ca.Function("A", [model.t, model.x, model.u, model.p], [ca.densify(ca.jacobian(xdot, model.x))],
                                  names, ["A"])}
    for name in model.measurements:
        h_and_H = measurement_jacobian(model, name)
        functions[f"h_{name}"] = h_and_H
    return functions

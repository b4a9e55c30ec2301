"""The backward step of the fixed-interval Rauch–Tung–Striebel smoothers (registers no family).

Rauch, Tung & Striebel (1965), "Maximum likelihood estimates of linear dynamic systems", AIAA J.
3(8); the unscented form is Särkkä (2008), "Unscented Rauch–Tung–Striebel smoother", IEEE Trans.
Automatic Control 53(3). Given the filtered x_k, P_k of a forward run and the smoothed
x^s_{k+1}, P^s_{k+1}, one backward step predicts from (x_k, P_k) over step k + 1 of the run, with
the family's own prediction (the same f_d, discretisation and process noise as the forward filter):

    x^-, P^-  and the cross-covariance  D = Cov(x_k, x_{k+1} | k)
        EKF: D = P_k F^T                 UKF: D = sum_i W_i (X_i - x_k)(Y_i - x^-)^T
    G     = D (P^-)^-1                   (Cholesky of P^-; not positive definite: SYMKF_ERR_NOT_PD)
    x^s_k = x_k + G (x^s_{k+1} - x^-)
    P^s_k = P_k + G (P^s_{k+1} - P^-) G^T   (lower half computed, mirrored; not PSD: SYMKF_ERR_NOT_PD)

The prediction is recomputed from the filtered row instead of being stored by the forward run: the
forward loop stays as it is, the history a smoother needs is the run's x and P (n + n^2 numbers per
step instead of 3n + 3n^2 with x^-, P^- and F), and any run's result can be smoothed afterwards.
A step whose update was masked or gated has x_{k+1} = x^- (the backward step is then a pure
prediction step, as it must be); the C loop's rule for steps that failed is in
``codegen/c_backend/smooth_loop.py``. On a manifold (the MEKF) the same step runs in error
coordinates: D = P_k F^T with the error-state F, and the correction is retracted onto x_k.
"""
from __future__ import annotations

import casadi as ca

from .. import linalg
from ..model_functions import Symbols
from ..spec import STATUS_DOMAIN, STATUS_NOT_PD, Arg, Kernel
from .framework import make_kernel

#: The smoother's own arguments: the smoothed state of step k + 1 in, of step k out.
SMOOTHED = ("xs", "Ps")
#: Inputs read from the forward run at each backward step (t, dt, u of step k + 1; x, P of row k).
PER_STEP = ("t", "dt", "u", "x", "P")


def smoothed_symbols(symbols: Symbols, P: ca.SX, P_unit: str) -> tuple[dict, dict]:
    """Symbols and Args of ``xs`` and ``Ps`` (the same names in and out, like a filter's x and P);
    Ps has the shape of the filter's P (n x n, or the error state's on a manifold)."""
    n, m = symbols.model.nx, P.shape[0]
    x_arg = symbols.arg["x"]
    return ({"xs": ca.SX.sym("xs", n), "Ps": ca.SX.sym("Ps", m, m)},
            {"xs": Arg("xs", (n, 1), x_arg.unit, "smoothed state estimate (input: of step k + 1; output: of step k)"),
             "Ps": Arg("Ps", (m, m), P_unit, "smoothed covariance (input: of step k + 1; output: of step k)")})


def backward_step(x: ca.SX, P: ca.SX, smoothed: dict, x_pred: ca.SX, P_pred: ca.SX, D: ca.SX, ok: ca.SX,
                  chart=None, domain=1):
    """x^s_k, P^s_k and the status (DOMAIN unless ``domain``; NOT_PD unless ``ok``, P^- has a
    Cholesky factor and P^s_k is positive semi-definite: in a float build the sum
    P_k + G (P^s_{k+1} - P^-) G^T can cancel to a negative variance, which is reported, not kept). With a manifold ``chart`` the correction is made in error coordinates:
    x^s_k = x_k (+) G (x^s_{k+1} (-) x^-) (the covariance is not transported between charts,
    the first-order error-state smoother, as the MEKF's reset)."""
    L, ok_pred = linalg.cholesky(P_pred)
    G = linalg.cholesky_solve(L, D.T).T                    # G = D (P^-)^-1, P^- symmetric
    if chart is None:
        x_out = x + G @ (smoothed["xs"] - x_pred)
    else:
        x_out = chart.retract(x, G @ chart.local(smoothed["xs"], x_pred))
    change = linalg.sandwich(G, smoothed["Ps"] - P_pred)
    P_out = linalg.symmetric(P.shape[0], lambda i, j: linalg.symmetric_part(P, i, j) + change[i, j])
    ok_out = linalg.psd_flag(P_out)          # a smoothed P that lost its PSD to round-off is refused, never kept
    status = linalg.select(domain, linalg.select(ok * ok_pred * ok_out, 0, STATUS_NOT_PD), STATUS_DOMAIN)
    return [("xs", x_out), ("Ps", P_out), ("status", status)]


def smooth_kernel(name: str, doc: str, symbols: Symbols, extra_sym: dict, extra_arg: dict, inputs: list[str],
                  prediction, chart=None, domain=1) -> Kernel:
    """The backward step ``name`` of a family whose prediction from (x, P) gives
    ``prediction = (x^-, P^-, D, ok)``, as a kernel with ``backward = ("xs", "Ps")``; ``inputs``:
    the prediction's kernel inputs (xs and Ps are appended); ``extra_sym``/``extra_arg``: the
    family's own symbols (its P and Q); ``chart``, ``domain``: see :func:`backward_step`."""
    P = extra_sym.get("P", symbols.sym["P"])
    sym, arg = smoothed_symbols(symbols, P, extra_arg.get("P", symbols.arg["P"]).unit)
    outputs = backward_step(symbols.sym["x"], P, sym, *prediction, chart=chart, domain=domain)
    kernel = make_kernel(name, doc, symbols, {**extra_sym, **sym}, {**extra_arg, **arg},
                         list(inputs) + list(SMOOTHED), outputs)
    return Kernel(kernel.name, kernel.function, kernel.doc, kernel.inputs, kernel.outputs,
                  per_step=tuple(a.name for a in kernel.inputs if a.name in PER_STEP), backward=SMOOTHED)


def cross_covariance(weights: list, offsets: list[ca.SX], moved: list[ca.SX]) -> ca.SX:
    """D = sum_i W_i (X_i - x)(Y_i - x^-)^T, term by term in order (Särkkä 2008's C_{k+1})."""
    n = offsets[0].shape[0]
    return sum((w * a @ b.T for w, a, b in zip(weights, offsets, moved)), ca.SX.zeros(n, n))

"""The iterated EKF update (Gauss-Newton), an option of the EKF family: ``ekf_iterations`` > 1.

Bell & Cathey, "The iterated Kalman filter update as a Gauss-Newton method", IEEE TAC 38(2),
1993, eq. (8): from the prediction x-, P-, iterate i = 0, 1, ... with x_0 = x-:

    H_i = dh/dx at x_i,  S_i = H_i P- H_i^T + R,  K_i = P- H_i^T S_i^-1,
    x_{i+1} = x- + K_i (z - h(x_i) - H_i (x- - x_i)),

a fixed count of ``ekf_iterations`` linearisations (generated unrolled: no loop, no branch in C)
that stops early, in effect, once a step moves no state by more than ``ekf_iteration_tolerance``
of its prior standard deviation (the later iterations keep x and their K, H). The covariance is
the Joseph form with the K, H of the last iteration that moved x. The innovation y, S reported
and gated are the first iteration's (those of the EKF: the gate decides as for the EKF). With one
iteration it is the EKF update of ``kalman.py``, term for term.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import casadi as ca

from .. import linalg
from ..model_functions import ModelFunctions, Symbols
from ..spec import CodegenConfig, ConfigError, option
from .framework import innovation, masked_noise


@dataclass(frozen=True)
class IteratedOptions:
    """The EKF's iterated-update options."""

    iterations: int = option(1, "EKF update linearisations (Gauss-Newton iterations; 1: the plain EKF update)")
    iteration_tolerance: float = option(0.0, "stop iterating once no state moves by more than this many of its "
                                             "prior standard deviations (0: always all iterations)")

    prefix: ClassVar[str] = "ekf_"

    @classmethod
    def of(cls, config: CodegenConfig) -> "IteratedOptions":
        p = cls.prefix
        chosen = cls(int(config.get(f"{p}iterations", 1)), float(config.get(f"{p}iteration_tolerance", 0.0)))
        if chosen.iterations < 1 or chosen.iterations > 50 or not chosen.iteration_tolerance >= 0:
            raise ConfigError(f"{p}iterations must be 1..50 and {p}iteration_tolerance >= 0; got "
                              f"{chosen.iterations}, {chosen.iteration_tolerance}")
        return chosen

    def still_moving(self, step, previous, sigma) -> ca.SX:
        """1 if some component of ``step - previous`` exceeds the tolerance times its sigma."""
        n = step.shape[0]
        return sum((ca.fabs(step[j] - previous[j]) > self.iteration_tolerance * sigma[j] for j in range(n)), 0) > 0


@dataclass(frozen=True)
class MekfIteratedOptions(IteratedOptions):
    """The MEKF's iterated-update options (``mekf_iterations``, ``mekf_iteration_tolerance``): the
    same Gauss-Newton iterations on the error state delta of the prior's chart (codegen/families/mekf.py)."""

    prefix: ClassVar[str] = "mekf_"


def _linearised_step(fns: ModelFunctions, symbols: Symbols, name: str, msym: dict, wrap, x_prior, P, x_i):
    """One Gauss-Newton step from x_i: (x_next, K, H, y_i, S_i, L_i, ok)."""
    s = symbols.sym
    z_pred, H_full = fns.h_and_jac[name](s["t"], x_i, s["u"], s["p"], msym["q"])
    mask = msym["mask"]
    H = ca.diag(mask) @ H_full
    y = innovation(msym["z"], z_pred, mask, wrap)
    S = linalg.symmetrize(H @ P @ H.T + masked_noise(msym["R"], mask))
    L, ok = linalg.cholesky(S)
    K = linalg.cholesky_solve(L, H @ P).T
    return x_prior + K @ (y - H @ (x_prior - x_i)), K, H, y, S, L, ok


def iterated_update_expr(symbols: Symbols, fns: ModelFunctions, name: str, msym: dict, wrap, x, P, t):
    """The iterated update: the outputs of ``kalman.ekf_update_expr`` (x+, P+, y, S, ok, nis)."""
    options = IteratedOptions.of(fns.config)
    n = symbols.model.nx
    sigma = prior_sigmas(P)
    x_next, K, H, y, S, L, ok = _linearised_step(fns, symbols, name, msym, wrap, x, P, x)
    x_i, active = x, ca.SX(1)
    for _ in range(options.iterations - 1):
        active = active * options.still_moving(x_next, x_i, sigma)      # once still: x, K, H kept
        x_i = linalg.select(active, x_next, x_i)
        step = _linearised_step(fns, symbols, name, msym, wrap, x, P, x_i)
        x_next = linalg.select(active, step[0], x_next)
        K, H = linalg.select(active, step[1], K), linalg.select(active, step[2], H)
        ok = ok * linalg.select(active, step[6], 1)
    I_KH = ca.SX.eye(n) - K @ H
    R = masked_noise(msym["R"], msym["mask"])
    P_new = linalg.sandwich(I_KH, P) + linalg.sandwich(K, R)           # Joseph form at the last iterate
    nis = ca.sumsqr(linalg.solve_lower(L, y))                         # the first iteration's: the EKF's gate
    return x_next, P_new, y, S, ok * linalg.psd_flag(P), nis


def iterations(config: CodegenConfig, options: type = IteratedOptions) -> int:
    return options.of(config).iterations


def prior_sigmas(P) -> list:
    """sqrt(P_jj) (1 where P_jj <= 0): the scale of the tolerance test."""
    return [ca.sqrt(linalg.guarded(P[j, j], P[j, j] > 0)) for j in range(P.shape[0])]

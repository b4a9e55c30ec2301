"""NumPy reference of the square-root multiplicative EKF (``codegen/families/srmekf.py``): the MEKF
of :class:`~symkf.runtime.reference.manifold.ManifoldReference` (its chart, F, H and Q_d written out
there) carrying the factor L of the error covariance, P = L L^T, in the array form (Kailath, Sayed &
Hassibi, Linear Estimation, 2000, sec. 12.3):

- prediction: x- = f_d(x) projected, L- = qr[F L, C] with C C^T = Q_d (``psd_factor``);
- update: [[chol(R), H L], [0, L]] triangularised to [[S^1/2, 0], [K_b, L+]] (numpy.linalg.qr),
  d = K_b S^-1/2 y, reset x+ = x (+) d.

What ``ManifoldReference`` covers, this covers (the additive or continuous noise of a model's
``noise()``, the step or series transition): e.g. models/marg_mekf.py. Compiled and reference agree
to round-off (tests/runtime/test_square_root_mekf.py)."""
from __future__ import annotations

import numpy as np
from scipy.linalg import solve_triangular

from symkf.runtime.covariance_form import psd_factor
from .kalman import ReferenceFilter
from .manifold import ManifoldReference
from .square_root import CarriesFactor, triangularize


class SquareRootManifoldReference(CarriesFactor, ManifoldReference):
    """The square-root MEKF ("srmekf") in NumPy; ``L`` carried, ``P`` = L L^T read."""

    def __init__(self, model, family: str, x0, P0, Q, R: dict | None = None, p=None, side: str = "right",
                 transition: str | None = None):
        if family != "srmekf":
            raise ValueError("family: expected 'srmekf'")
        super().__init__(model, "mekf", x0, P0, Q, R, p, side=side, transition=transition)
        self.family = family

    def predict(self, t: float, dt: float, u=None) -> None:
        if u is not None:
            self.u = np.array(u, float)
        noise = psd_factor(self.process_noise(t, dt))
        x_next, F = self.mekf_transition(t, dt)
        self.x, self.L = x_next, triangularize(np.hstack([F @ self.L, noise]))

    def update(self, z, name: str, t: float, q=(), mask=None) -> None:
        z = np.asarray(z, float)
        mask = np.ones_like(z) if mask is None else np.asarray(mask, float)
        R_root = np.linalg.cholesky(ReferenceFilter.masked_noise(self.R[name], mask))
        z_pred = self._h(name, t, self.x, q)
        H = mask[:, None] * (np.array(self.functions.jac_h[name](t, self.x, self.u, self.p, q))
                             @ self.retract_jacobian(self.x))
        y = ReferenceFilter.innovation(z, z_pred, mask, self.wrap[name])
        m, n = H.shape
        post = triangularize(np.block([[R_root, H @ self.L], [np.zeros((n, m)), self.L]]))
        S_z, K_bar = post[:m, :m], post[m:, :m]
        self.x = self.retract(self.x, K_bar @ solve_triangular(S_z, y, lower=True))
        self.L = post[m:, m:]
        self.y, self.S = y, S_z @ S_z.T

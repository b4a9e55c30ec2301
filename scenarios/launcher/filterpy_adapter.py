"""FilterPy's EKF and UKF driven by our compiled model functions (benchmark comparison only).

FilterPy (``pip install -e .[bench]``) supplies the filter algebra; f_d, F = df_d/dx, h and
H = dh/dx are our generated C kernels, so the comparison isolates the filter implementation.
Same conventions: Q dt as discrete process noise, Julier sigma points with the same kappa,
azimuth residuals wrapped to (-pi, pi]. Importing this module raises ImportError without FilterPy.
"""
from __future__ import annotations

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter, JulierSigmaPoints, UnscentedKalmanFilter

from symkf.models import launcher as L
from symkf.runtime.reference import wrap_angle


class _ModelCalls:
    """Our compiled kernels fd, jac_fd, h_radar, jac_h_radar bound to scratch buffers."""

    def __init__(self, model):
        n = 6
        self.buffers = {"t": np.zeros(1), "dt": np.zeros(1), "x": np.zeros(n), "u": np.zeros(0),
                        "p": np.array([L.GUIDANCE[k] for k in L.GUIDANCE_PARAMS]), "q": np.zeros(2),
                        "F": np.zeros((n, n), order="F"), "z": np.zeros(3), "H": np.zeros((3, n), order="F")}
        # fd writes x in place: give it its own x buffer so the input is not overwritten mid-call
        self.fd_buffers = dict(self.buffers, x=np.zeros(n))
        bind = model.backend.bind
        self._fd, self._F = bind("fd", self.fd_buffers), bind("jac_fd", self.buffers)
        self._h, self._H = bind("h_radar", self.buffers), bind("jac_h_radar", self.buffers)

    def fd(self, x, dt, t):
        """FilterPy's fx(x, dt, **fx_args) convention."""
        b = self.fd_buffers
        b["x"][:], b["t"][0], b["dt"][0] = x, t, dt
        self._fd()
        return b["x"].copy()

    def F(self, x, t, dt):
        b = self.buffers
        b["x"][:], b["t"][0], b["dt"][0] = x, t, dt
        self._F()
        return b["F"].copy()

    def h(self, x, t, q):
        b = self.buffers
        b["x"][:], b["t"][0], b["q"][:] = x, t, q
        self._h()
        return b["z"].copy()

    def H(self, x, t, q):
        b = self.buffers
        b["x"][:], b["t"][0], b["q"][:] = x, t, q
        self._H()
        return b["H"].copy()


def _residual(a, b):
    d = np.subtract(a, b)
    d[2] = wrap_angle(d[2])
    return d


def make_filterpy_filter(model, family: str, x0, P0, Q, kappa: float):
    """A ``step(t, dt, z, q)`` closure running FilterPy's filter on our compiled model."""
    calls = _ModelCalls(model)
    R = np.diag(np.square(L.RADAR_SIGMA))
    if family == "ekf":
        ekf = ExtendedKalmanFilter(dim_x=6, dim_z=3)
        ekf.x, ekf.P, ekf.R = np.array(x0, float), np.array(P0, float), R

        def step(t, dt, z, q):
            ekf.F = calls.F(ekf.x, t, dt)
            ekf.Q = Q * dt
            ekf.x = calls.fd(ekf.x, dt, t)
            ekf.P = ekf.F @ ekf.P @ ekf.F.T + ekf.Q
            ekf.update(z, calls.H, calls.h, args=(t + dt, q), hx_args=(t + dt, q), residual=_residual)
        return step
    points = JulierSigmaPoints(6, kappa=kappa)
    ukf = UnscentedKalmanFilter(dim_x=6, dim_z=3, dt=0.05, hx=calls.h, fx=calls.fd, points=points,
                                residual_z=_residual)
    ukf.x, ukf.P, ukf.R = np.array(x0, float), np.array(P0, float), R

    def step(t, dt, z, q):
        ukf.Q = Q * dt
        ukf.predict(dt=dt, t=t)
        ukf.update(z, t=t + dt, q=q)
    return step

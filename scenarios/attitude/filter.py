"""Attitude filters of paper 000 over the generated kernels.

:class:`AttitudeFilter` is a thin view of buffers bound once to the attitude model's generated
manifold filters (``kind`` = "mekf": the generic multiplicative EKF, "ukf": the paper's
separated-space UKF "sukf", "aukf": its full augmented form; codegen/families/mekf.py and
quaternion_filters.py document the equations);
:class:`~symkf.scenarios.attitude.reference.ReferenceAttitudeFilter` is the paper's algebra written in NumPy.

Conventions: x = [q; b] with q scalar-last (paper 000), P the 6x6 covariance of [δp; δb],
δp the vector part of δq = q ⊗ q̂⁻¹ (half-angle units). Q: 6x6 PSD of [η_a; η_b]; R: 3x3
covariance of the star-tracker noise rotation vector η_s. Defaults: Table 1.

Bad input: the contract of every filter (:mod:`symkf.runtime.contract`): shapes, dt, P and
Q symmetric PSD, R PD; an initial quaternion is normalised if its norm is within 1e-3 of 1 and
rejected otherwise; a star-tracker quaternion with NaN/Inf raises SymkfError (NONFINITE) unless
``nan="mask"`` (pass ``None`` to skip a missing measurement; in :meth:`AttitudeFilter.run` a NaN
row means "no measurement"); a star-tracker quaternion whose norm is off 1 by more than 1e-3 is
rejected by the kernel (SYMKF_ERR_DOMAIN), smaller deviations are normalised. A failed step
raises and leaves x, P and t unchanged. The NumPy reference lives in :mod:`symkf.scenarios.attitude.reference`.

The adapter only renames: step(omega_g, dt, q_s) is ``Filter.step(t, dt, q_s, "star_tracker",
u=omega_g)``, so the generic C fast path of :class:`~symkf.runtime.filters.Filter` serves it.
"""
from __future__ import annotations

import numpy as np

from symkf.models import attitude as model
from symkf.runtime import contract
from symkf.runtime.filters import Filter
from symkf.runtime.runs import RunResult
from .reference import DEFAULT_KAPPA, KINDS, ReferenceAttitudeFilter, _initial_state

#: The generated filter behind each of paper 000's filters: the generic multiplicative EKF, the
#: separated-noise UKF and the augmented UKF of the manifold families.
FILTER_OF_KIND = {"mekf": "mekf", "ukf": "sukf", "aukf": "aukf"}


class AttitudeFilter(Filter):
    """MEKF, the paper's UKF or the augmented UKF of a compiled ``attitude`` model (a thin
    :class:`~symkf.runtime.filters.Filter`: the paper's argument names over the generic one).

    Args:
        compiled: ``symkf.runtime.load("attitude")``.
        kind: "mekf", "ukf" or "aukf".
        q0, b0, P0: initial quaternion, gyro bias (rad/s) and 6x6 error covariance.
        Q, R: noise (defaults: Table 1 via models/attitude.py).
        kappa: UKF scaling (ignored by the MEKF).
        gate: innovation gates as :class:`~symkf.runtime.filters.Filter` (default "none": paper
            000 fuses every star-tracker sample).

    Attributes (read-only views): x, q, b, P; y and S of the last update (innovation δp_s, P^yy).
    """

    MEASUREMENT = "star_tracker"

    def __init__(self, compiled, kind: str, q0, b0, P0, Q=None, R=None, kappa: float = DEFAULT_KAPPA,
                 gate="none"):
        if kind not in KINDS:
            raise ValueError(f"kind: expected one of {KINDS}, got {kind!r}")
        x, P = _initial_state(q0, b0, P0)
        Q = model.process_noise_psd() if Q is None else Q
        R = {self.MEASUREMENT: model.star_tracker_covariance() if R is None else R}
        options = {} if kind == "mekf" else {"kappa": kappa}
        super().__init__(compiled, FILTER_OF_KIND[kind], x, P, Q, R=R, gate=gate, **options)
        self.kind = kind

    y = property(lambda self: Filter.y(self, self.MEASUREMENT), doc="Innovation δp_s of the last update (eq 50).")
    S = property(lambda self: Filter.S(self, self.MEASUREMENT), doc="Innovation covariance P^yy of the last update.")
    q = property(lambda self: self.x[0:4], doc="Attitude quaternion estimate (scalar-last).")
    b = property(lambda self: self.x[4:7], doc="Gyro bias estimate, rad/s.")

    def body_rate(self, omega_g) -> np.ndarray:
        """Eq (53): ω̂ = ω_g + b̂."""
        return contract.finite_array("omega_g", omega_g, (3,)) + self.b

    def predict(self, omega_g, dt: float) -> None:
        """Propagate over dt with gyro output omega_g (rad/s)."""
        super().predict(self.t, dt, u=contract.finite_array("omega_g", omega_g, (3,)))

    def update(self, q_s, nan: str = "raise") -> int:
        """Star-tracker update with quaternion q_s (MEKF and separated UKF)."""
        if not self.spec.update:
            raise ValueError("update: the augmented UKF updates only inside step(omega_g, dt, q_s)")
        return super().update(q_s, nan=nan)

    def step(self, omega_g, dt: float, q_s=None, nan: str = "raise") -> int:
        """Propagate over dt, then update with q_s if it is not None — one compiled call."""
        if q_s is None:
            self.predict(omega_g, dt)
            return 0
        if omega_g is None:
            raise ValueError("omega_g: the gyro output (3,) is required")
        return Filter.step(self, self.t, dt, q_s, self.MEASUREMENT, u=omega_g, nan=nan)

    def run(self, omega_g, dt, q_s) -> RunResult:
        """All steps in one compiled call (the C run loop). Step k propagates over dt[k] (one dt
        for every step, or one per step: the run rule of :func:`symkf.runtime.contract.run_steps`)
        with omega_g[k] and updates with q_s[k] unless that row has NaN (no measurement)."""
        shape = np.shape(omega_g)
        n_steps = shape[0] if len(shape) == 2 else 0
        omega_g = contract.finite_array("omega_g", omega_g, (n_steps, 3))
        dt = np.broadcast_to(contract.as_array("dt", dt, np.shape(dt)), (n_steps,))
        return self.run_steps(dt, q_s, self.MEASUREMENT, u=omega_g, nan="mask")


def attitude_filter(kind: str, q0, b0, P0, backend: str = "auto", **options) -> AttitudeFilter:
    """Load (building if stale) the attitude model and return its ``kind`` filter."""
    from symkf.runtime import load
    return AttitudeFilter(load("attitude", backend=backend), kind, q0, b0, P0, **options)


#: ReferenceAttitudeFilter: tests/test_contract.py imports it from here.
__all__ = ["AttitudeFilter", "ReferenceAttitudeFilter", "attitude_filter"]

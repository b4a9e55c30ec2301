"""The gradient-descent filter of paper 001 in the paper's vocabulary, over the public Filter API.

The compiled filters ``gd_simple`` (eq (31)) and ``gd_full`` (eqs (26)-(30)) of
``codegen/families/gradient_descent.py`` are plain :class:`~symkf.runtime.filters.Filter` objects:
``step(t, dt, z, "marg", u=gyro, mask=...)`` and ``run(times, z, "marg", u=gyro)`` with z the
accelerometer sample (measurement ``"imu"``) or accelerometer and magnetometer samples
(``"marg"``, 6 components; a missing sample is masked). What is here:

- :func:`make_filter`: such a Filter from the paper's gains β, α (checked) and a unit q0;
- :func:`initial_orientation`: the TRIAD orientation from one sample (the ``gd_initial_<m>`` kernel);
- :func:`samples`: a recording's samples as the measurement z.

Recordings and the BROAD metric are experiment code: ``symkf.scenarios.marg.data`` / ``.broad_metric``.
"""
from __future__ import annotations

import numpy as np

from symkf.models.marg import ALPHA_DEFAULT, BETA_MADGWICK
from symkf.runtime import contract
from symkf.runtime.backends import SymkfError
from symkf.runtime.filters import Filter

#: Largest accepted deviation of an initial quaternion's norm from 1.
UNIT_TOLERANCE = 1e-6
#: Measurement names of the gradient-descent filters: 6-axis and 9-axis.
MODES = ("imu", "marg")


def make_filter(compiled, form: str = "simple", beta: float = BETA_MADGWICK, alpha: float = ALPHA_DEFAULT,
                q0=None) -> Filter:
    """Filter ``gd_<form>`` of ``symkf.runtime.load("marg")``: β in rad/s (eq (30)-(31), >= 0), α
    (eq (28), > 1, full form only), q0 a unit quaternion (scalar-last, sensor -> north-west-up;
    default identity, or :func:`initial_orientation` of the first sample)."""
    q0 = np.array([0.0, 0.0, 0.0, 1.0]) if q0 is None else unit("q0", q0)
    return Filter(compiled, f"gd_{form}", q0, p=[_beta(beta), _alpha(alpha)])


def initial_orientation(compiled, z, measurement: str = "marg") -> np.ndarray:
    """Initial orientation from one sample z (TRIAD; 6-axis ``"imu"``: heading from a sensor axis)."""
    if measurement not in MODES:
        raise ValueError(f"measurement: expected one of {MODES}, got {measurement!r}")
    kernel = f"gd_initial_{measurement}"
    dtype = getattr(compiled.backend, "dtype", np.dtype(np.float64))
    buffers = {"z": contract.finite_array("z", z, (3 if measurement == "imu" else 6,)).astype(dtype),
               "x": np.zeros(4, dtype)}
    code = compiled.backend.bind(kernel, buffers)()
    if code:
        raise SymkfError(kernel, code, "acc and mag must be finite, non-zero and not parallel")
    return buffers["x"].astype(float)


def samples(acc, mag, measurement: str = "marg") -> np.ndarray:
    """The measurement z of a record: acc (N, 3) for ``"imu"``, [acc, mag] (N, 6) for ``"marg"``."""
    return np.asarray(acc, dtype=float) if measurement == "imu" else np.hstack([acc, mag])


def unit(name: str, value) -> np.ndarray:
    q = contract.finite_array(name, value, (4,))
    norm = np.linalg.norm(q)
    if abs(norm - 1) > UNIT_TOLERANCE:
        raise ValueError(f"{name}: expected a finite unit quaternion [x, y, z, w], got norm {norm}")
    return q


def _beta(value) -> float:
    value = contract.real("beta", value)
    if value < 0:
        raise ValueError(f"beta: expected a finite number >= 0, got {value}")
    return value


def _alpha(value) -> float:
    value = contract.real("alpha", value)
    if value <= 1:
        raise ValueError(f"alpha: eq (28) needs alpha > 1, got {value}")
    return value


__all__ = ["MODES", "initial_orientation", "make_filter", "samples", "unit"]

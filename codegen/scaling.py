"""The scaled state: a model rewritten on well-conditioned numbers for single precision.

A model declares per state a scale s_i and an offset o_i (``Model.state(..., scale=, offset=)``).
A scaled build generates every filter from the model written in

    x = o + S x~,    S = diag(s),

so the filters carry x~ and P~ = S^-1 P S^-1 instead of x and P. The rewritten equations are
derived here by CasADi from the model's own f and h (one source of truth):

    f~(t, x~, u, p, w) = S^-1 f(t, o + S x~, u, p, w),    h~(t, x~, u, p, q) = h(t, o + S x~, u, p, q),

and every Jacobian, sigma point and discretisation downstream is the families' usual one, applied
to f~ and h~. Why (measured in docs/flight_bundle.md): the launcher's P spans metres against
1e-8 rad (condition number near 1e18), beyond what float's 24-bit significand survives in
F P F^T or a Cholesky factor, and a geocentric radius near 6.4e6 m has a float spacing of 0.5 m,
the size of the filter's whole error; with the Earth's radius and the launch site as offsets, the
carried numbers are altitude-like and their spacing is centimetres.

Measurements are not scaled: z, R, the innovation y and S keep the model's units (Cholesky and
the triangular solves are insensitive to a diagonal scaling of S, and angle wrapping stays
(-pi, pi]). Quaternion states keep scale 1 and offset 0 (the manifold filters normalise them).
Scales are powers of two and offsets single-precision numbers (models/base.py), so converting
between x and x~ in double (the Python runtime) and in float (flight code) agrees exactly.
"""
from __future__ import annotations

import copy

import casadi as ca
import numpy as np

from symkf.models import Model
from symkf.models.base import Variable
from symkf.models.errors import ModelError
from symkf.models.estimation import augmented


def scaling_arrays(model: Model) -> tuple[np.ndarray, np.ndarray]:
    """(scale, offset) per state, as declared."""
    return np.array(model.state_scale, dtype=float), np.array(model.state_offset, dtype=float)


def scaled_model(model: Model) -> Model:
    """The model written in x~ = (x - offset) / scale (module docstring); the model itself is not
    changed. A model with no declared scaling is returned as it is."""
    if not model.has_scaling or model.scaled_state:
        return model
    scale, offset = scaling_arrays(model)
    for qs in model.quaternions:
        block = slice(qs.index, qs.index + 4)
        if np.any(scale[block] != 1.0) or np.any(offset[block] != 0.0):
            raise ModelError(f"model '{model.name}': quaternion state '{qs.name}' cannot be scaled")
    x = model.x
    x_scaled = ca.vertcat(*[ca.SX.sym(v.name) for v in model.states])
    physical = ca.DM(offset) + ca.DM(scale) * x_scaled            # x = o + S x~
    scaled = copy.copy(model)
    scaled._symbols = {**model._symbols, "x": [x_scaled[i] for i in range(model.nx)]}
    scaled.states = [_scaled_variable(v, s, o) for v, s, o in zip(model.states, scale, offset)]
    scaled.f = ca.substitute(model.f, x, physical) / ca.DM(scale)
    if model.discrete_step is not None:                           # x~_{k+1} = (φ(o + S x~_k) - o) / S
        dt, step = model.discrete_step
        scaled.discrete_step = (dt, (ca.substitute(step, x, physical) - ca.DM(offset)) / ca.DM(scale))
    scaled.measurements = {name: copy.copy(m) for name, m in model.measurements.items()}
    for m in scaled.measurements.values():
        m.h = ca.substitute(m.h, x, physical)
    scaled.scaled_state = True
    return scaled


def _scaled_variable(v: Variable, scale: float, offset: float) -> Variable:
    if scale == 1.0 and offset == 0.0:
        return v
    return Variable(v.name, f"{scale:.9g} {v.unit}",
                    f"{v.description}; scaled: x~ = (x - {offset:.9g} {v.unit}) / {scale:.9g} {v.unit}")


def model_for(model: Model, config) -> Model:
    """The model a build of ``config`` generates from: its estimated parameters as states
    (models/estimation.py), then scaled when ``config.scaled``."""
    model = augmented(model)
    return scaled_model(model) if config.scaled else model

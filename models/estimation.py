"""Parameters estimated by declaration: a model marks a runtime parameter as estimated, and the
filters carry it as a state (Simon, Optimal State Estimation, 2006, sec. 13.4: state augmentation
for parameter estimation).

    m.param("drag", "1/s", "linear drag coefficient", 0.1)
    estimate(m, "drag", sigma=0.02, random_walk=1e-6)     # initial value: the parameter's default

:func:`augmented` is the model the generator builds from (codegen/scaling.py ``model_for``): the
parameter's symbol becomes the last state(s), with dynamics d(param)/dt = w (a random walk of
power spectral density ``random_walk``; 0: a constant), so f and h are unchanged symbols and CasADi
derives the augmented Jacobians. A model without ``noise()`` gets the walk on the state itself (its
additive Q grows by one row and column per parameter); a model with noises gets one noise per
parameter (its Q of the noises grows likewise). The description lists each estimated parameter
with its state index, initial value, sigma, random walk and Q index
(``estimated_parameters``); runtime/estimated.py fills x0, P0, Q from it and reports the estimate
and its sigma by name.
"""
from __future__ import annotations

import copy

import casadi as ca

from .base import Model, Variable
from .errors import ModelError


def estimate(model: Model, name: str, sigma: float, random_walk: float = 0.0) -> None:
    """Mark the runtime parameter ``name`` as estimated: initial value its default, initial
    standard deviation ``sigma`` (> 0, in its unit), random-walk intensity ``random_walk``
    ((unit)^2 / s, >= 0; 0: a constant)."""
    names = [v.name for v in model.params]
    if name not in names:
        raise ModelError(f"model '{model.name}': no parameter '{name}' to estimate; parameters: {names}")
    if not (sigma > 0 and random_walk >= 0):
        raise ModelError(f"model '{model.name}': estimated parameter '{name}' needs sigma > 0 and random_walk >= 0")
    if model.discrete_step is not None or model.quaternions:
        raise ModelError(f"model '{model.name}': estimated parameters are for models without a discrete step or "
                         "quaternion states")
    model.estimated[name] = {"name": name, "initial": float(model.param_defaults[names.index(name)]),
                             "sigma": float(sigma), "random_walk": float(random_walk)}


def augmented(model: Model) -> Model:
    """The model with its estimated parameters as states (module docstring); unchanged if none."""
    if not model.estimated or any(v.name in model.estimated for v in model.states):
        return model
    names = [v.name for v in model.params]
    keep = [i for i, v in enumerate(model.params) if v.name not in model.estimated]
    moved = [names.index(name) for name in model.estimated]
    p = model._symbols["p"]
    new = copy.copy(model)
    new._symbols = {**model._symbols, "x": model._symbols["x"] + [p[i] for i in moved], "p": [p[i] for i in keep]}
    new.states = model.states + [Variable(v.name, v.unit, f"{v.description} (estimated parameter)")
                                 for v in (model.params[i] for i in moved)]
    new.params, new.param_defaults = [model.params[i] for i in keep], [model.param_defaults[i] for i in keep]
    new.state_scale = list(model.state_scale) + [1.0] * len(moved)
    new.state_offset = list(model.state_offset) + [0.0] * len(moved)
    walk = []
    if model.noises:
        w = [ca.SX.sym(f"w_{names[i]}") for i in moved]
        new._symbols["w"] = model._symbols["w"] + w
        new.noises = model.noises + [Variable(f"w_{names[i]}", f"({model.params[i].unit})/s^0.5",
                                              f"random walk of the estimated parameter {names[i]}") for i in moved]
        walk = w
    else:
        walk = [ca.SX(0)] * len(moved)
    new.f = ca.vertcat(model.f, *walk)
    new.estimated = {name: dict(record, state=model.nx + k, q_index=(len(model.noises) + k) if model.noises
                                else model.nx + k) for k, (name, record) in enumerate(model.estimated.items())}
    return new

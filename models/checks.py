"""Authoring checks run by :meth:`Model.validate`: mistakes a model author makes that would
otherwise pass silently, end in a C compile error or a traceback deep in codegen.

Each check raises :class:`ModelError` with one line naming the model, the equation (``d<state>/dt``
or ``measurement '<name>'``) and the symbol at fault:

- a non-differentiable operation (floor, ceil, sign, fabs, fmod, remainder, fmin, fmax, copysign,
  if_else and comparisons) applied to an expression of the states: the EKF linearises and the
  UKF interpolates there, so a kink or jump in x gives wrong Jacobians. Allowed where the author
  says so (``set_dynamics(..., allow_nondifferentiable=["v"])``, ``measurement(...,
  allow_nondifferentiable=True)``); operations on time, inputs or parameters are always fine;
- a NaN or infinite constant in an equation;
- a process noise or a measurement's own parameter that no equation uses; a model-wide parameter
  no equation uses (:func:`check_parameters_used`, which codegen runs where the filters read
  parameters through f and h alone);
- measurement names whose generated C names collide (``rb`` and ``rb_run``: ``_run`` and ``_v``
  are suffixes of generated functions);
- degenerate sizes (:func:`check_sizes`): no state, no measurement, or more states (or outputs of
  one measurement) than :data:`MAX_STATES` (:data:`MAX_OUTPUTS`), past which a build takes hours
  and gigabytes; ``SYMKF_MAX_STATES`` / ``SYMKF_MAX_OUTPUTS`` raise the limits on purpose.
Expression types (MX, lists, strings, vectors) and sigma <= 0 are checked where they are given,
in :meth:`Model.set_dynamics` and :meth:`Model.measurement`.
"""
from __future__ import annotations

import math
import os
from typing import TYPE_CHECKING

import casadi as ca

from .errors import ModelError

if TYPE_CHECKING:
    from .base import Model

NONDIFFERENTIABLE = {ca.OP_FLOOR: "floor", ca.OP_CEIL: "ceil", ca.OP_SIGN: "sign", ca.OP_FABS: "fabs",
                     ca.OP_FMOD: "fmod", ca.OP_REMAINDER: "remainder", ca.OP_FMIN: "fmin", ca.OP_FMAX: "fmax",
                     ca.OP_COPYSIGN: "copysign", ca.OP_IF_ELSE_ZERO: "if_else", ca.OP_LT: "a comparison (<)",
                     ca.OP_LE: "a comparison (<=)", ca.OP_EQ: "a comparison (==)", ca.OP_NE: "a comparison (!=)"}


#: States a model may have unless ``$SYMKF_MAX_STATES`` allows more. The fused EKF/UKF kernels
#: grow about as n^3 (n sigma points, each an n x n update) and their compile time faster:
#: measured here (2 shared cores, gcc -O3, a chain model with EKF and UKF), 10 states built in 21 s
#: and 20 states in 228 s; the paper models have at most 17.
MAX_STATES = 48
#: Outputs one measurement may have unless ``$SYMKF_MAX_OUTPUTS`` allows more (S is m x m).
MAX_OUTPUTS = 48


def _limit(variable: str, default: int) -> int:
    """The limit ``$variable`` sets (an integer >= 1), else ``default``."""
    text = os.environ.get(variable, "")
    if not text:
        return default
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise ModelError(f"${variable}={text!r}: expected an integer >= 1")
    return value


def check_sizes(model: "Model") -> None:
    """At least one state and one measurement, and sizes within the documented limits."""
    if not model.states:
        raise ModelError(f"model '{model.name}': no states declared; declare them with model.state(name, unit, "
                         "description) before set_dynamics()")
    if not model.measurements:
        raise ModelError(f"model '{model.name}': no measurement declared; a filter needs at least one: add it with "
                         "model.measurement(name, [(output, unit, description, expression), ...], sigma=[...])")
    limit = _limit("SYMKF_MAX_STATES", MAX_STATES)
    if model.nx > limit:
        raise ModelError(f"model '{model.name}': {model.nx} states is past the limit of {limit} (build time and "
                         f"memory grow about as n^3; 20 states took about 4 minutes to build): set "
                         f"SYMKF_MAX_STATES={model.nx} to build it anyway")
    limit = _limit("SYMKF_MAX_OUTPUTS", MAX_OUTPUTS)
    for meas in model.measurements.values():
        if len(meas.outputs) > limit:
            raise ModelError(f"model '{model.name}': measurement '{meas.name}' has {len(meas.outputs)} outputs, past "
                             f"the limit of {limit}: split it into several measurements, or set "
                             f"SYMKF_MAX_OUTPUTS={len(meas.outputs)} to build it anyway")


def scalar_expression(model: str, what: str, value) -> ca.SX:
    """``value`` as a 1x1 SX, or ModelError saying what it is instead (MX, list, string, vector)."""
    if isinstance(value, (ca.MX, ca.Function)):
        raise ModelError(f"model '{model}': {what} is a CasADi {type(value).__name__}; models are SX: build "
                         "expressions from the symbols model.state()/input()/param()/noise() return")
    if isinstance(value, (str, bytes)):
        raise ModelError(f"model '{model}': {what} is a string ({value!r}), expected an SX expression or a number")
    if isinstance(value, (list, tuple, dict, set)):
        raise ModelError(f"model '{model}': {what} is a {type(value).__name__}; give one scalar expression")
    try:
        expr = ca.SX(value)
    except (NotImplementedError, TypeError, RuntimeError, ValueError):
        raise ModelError(f"model '{model}': {what} is a {type(value).__name__}, expected an SX expression "
                         "or a number") from None
    if expr.shape != (1, 1):
        raise ModelError(f"model '{model}': {what} has shape {expr.shape}, expected a scalar (1, 1); "
                         "give one component per output")
    return expr


def equations(model: "Model") -> list[tuple[str, ca.SX, bool]]:
    """(label, scalar expression, non-differentiable allowed) for every equation of the model."""
    rows = [(f"d{name}/dt", model.f[i], name in model.nondifferentiable_ok)
            for i, name in enumerate(model.state_names())]
    for meas in model.measurements.values():
        for i, out in enumerate(meas.outputs):
            rows.append((f"measurement '{meas.name}' component '{out.name}'", meas.h[i],
                         meas.name in model.nondifferentiable_ok))
    return rows


def check_equations(model: "Model") -> None:
    """Non-differentiable operations on states and non-finite constants, per equation."""
    states = {s.name() for s in model._symbols["x"]}
    for label, expr, allowed in equations(model):
        for node in _nodes(expr):
            if node.is_constant():
                value = float(node)
                if not math.isfinite(value):
                    raise ModelError(f"model '{model.name}': {label} contains the constant {value}")
            elif not allowed and not node.is_symbolic() and node.op() in NONDIFFERENTIABLE:
                used = sorted({s.name() for k in range(node.n_dep()) for s in ca.symvar(node.dep(k))} & states)
                if used:
                    raise ModelError(
                        f"model '{model.name}': {label} applies {NONDIFFERENTIABLE[node.op()]} to state "
                        f"'{used[0]}' (not differentiable where the filter linearises); if intended, pass "
                        f"allow_nondifferentiable to {'set_dynamics' if label.startswith('d') else 'measurement'}()")


def _nodes(expr: ca.SX):
    """Every node of a scalar SX expression graph, each once."""
    seen, stack = set(), [expr]
    while stack:
        node = stack.pop()
        key = node.element_hash()
        if key in seen:
            continue
        seen.add(key)
        yield node
        if not node.is_symbolic() and not node.is_constant():
            stack.extend(node.dep(k) for k in range(node.n_dep()))


def check_unused(model: "Model") -> None:
    """Every noise appears in the dynamics; every measurement depends on the state and uses each
    of its parameters and noises."""
    in_f = {s.name() for s in ca.symvar(model.f)}
    for var, sym in zip(model.noises, model._symbols["w"]):
        if sym.name() not in in_f:
            raise ModelError(f"model '{model.name}': noise '{var.name}' is declared but the dynamics do not use it")
    states = {s.name() for s in ca.vertsplit(model.x)}
    for meas in model.measurements.values():
        in_h = {s.name() for s in ca.symvar(meas.h)}
        if not in_h & states:
            raise ModelError(f"model '{model.name}': measurement '{meas.name}' does not depend on the state "
                             f"(its outputs use {sorted(in_h) or 'no symbol'}): a filter could learn nothing from it")
        for kind, variables, symbols in (("parameter", meas.params, meas.q), ("noise", meas.noise, meas.v)):
            for var, sym in zip(variables, ca.vertsplit(symbols)):
                if sym.name() not in in_h:
                    raise ModelError(f"model '{model.name}': measurement '{meas.name}' {kind} '{var.name}' is "
                                     "declared but not used by that measurement")


def check_parameters_used(model: "Model") -> None:
    """Every model-wide parameter appears in some equation. Not part of :meth:`Model.validate`:
    it holds only where the filters read parameters through f and h alone, which codegen knows
    (it runs this check for those filters; a filter's own gain may be a parameter too)."""
    used = {s.name() for s in ca.symvar(model.f)}
    for meas in model.measurements.values():
        used |= {s.name() for s in ca.symvar(meas.h)}
    for var, sym in zip(model.params, model._symbols["p"]):
        if sym.name() not in used:
            raise ModelError(f"model '{model.name}': parameter '{var.name}' is declared but no equation uses it")


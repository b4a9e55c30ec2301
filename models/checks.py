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
  are suffixes of generated functions).
Expression types (MX, lists, strings, vectors) and sigma <= 0 are checked where they are given,
in :meth:`Model.set_dynamics` and :meth:`Model.measurement`.
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING

import casadi as ca

from .errors import ModelError

if TYPE_CHECKING:
    from .base import Model

NONDIFFERENTIABLE = {ca.OP_FLOOR: "floor", ca.OP_CEIL: "ceil", ca.OP_SIGN: "sign", ca.OP_FABS: "fabs",
                     ca.OP_FMOD: "fmod", ca.OP_REMAINDER: "remainder", ca.OP_FMIN: "fmin", ca.OP_FMAX: "fmax",
                     ca.OP_COPYSIGN: "copysign", ca.OP_IF_ELSE_ZERO: "if_else", ca.OP_LT: "a comparison (<)",
                     ca.OP_LE: "a comparison (<=)", ca.OP_EQ: "a comparison (==)", ca.OP_NE: "a comparison (!=)"}


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


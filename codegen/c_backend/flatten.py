"""One SX Function with every call inlined: the filter step that runs in lockstep lanes.

A kernel's SX algorithm calls the model's functions (f_d and its Jacobian, h and its Jacobian,
f_d at the sigma points), which are written once in C and called (``never_inline``). The lockstep
run loop (c_backend/lockstep.py) evaluates a whole filter step for several Monte Carlo runs at
once, so it needs the step as one straight-line algorithm: :meth:`Flattener.flat` re-plays a function's
instructions operation by operation (``SX.binary``/``SX.unary``: the same IEEE operations on the
same operands, so the same numbers) and a call by re-playing the called function on the caller's
operands.

A called function that picks a branch at run time is replaced by one branch (a
:class:`Substitute`), and the condition under which the C would take another one is collected:
an event dispatcher (:class:`~symkf.codegen.discretize.EventBranches`) by its plain branch, taken
when no event lies in (t, t + dt]; the UKF's weight switch by its centre-free branch, taken when
the centre weight is exactly 0. The lockstep loop evaluates the conditions first and steps a run
in lanes only when all are 0 (they depend on t, dt and the constants: the same for every run).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import casadi as ca

#: CasADi operations re-played by arity (the rest have no place in a filter step: NotImplementedError).
BINARY = {ca.OP_ADD, ca.OP_SUB, ca.OP_MUL, ca.OP_DIV, ca.OP_POW, ca.OP_CONSTPOW, ca.OP_LT, ca.OP_LE, ca.OP_EQ,
          ca.OP_NE, ca.OP_AND, ca.OP_OR, ca.OP_IF_ELSE_ZERO, ca.OP_ATAN2, ca.OP_FMIN, ca.OP_FMAX, ca.OP_FMOD,
          ca.OP_COPYSIGN, ca.OP_HYPOT}
UNARY = {ca.OP_ASSIGN, ca.OP_NEG, ca.OP_SQ, ca.OP_TWICE, ca.OP_INV, ca.OP_NOT, ca.OP_SIGN, ca.OP_EXP, ca.OP_LOG,
         ca.OP_SQRT, ca.OP_SIN, ca.OP_COS, ca.OP_TAN, ca.OP_ASIN, ca.OP_ACOS, ca.OP_ATAN, ca.OP_SINH, ca.OP_COSH,
         ca.OP_TANH, ca.OP_ASINH, ca.OP_ACOSH, ca.OP_ATANH, ca.OP_FABS, ca.OP_FLOOR, ca.OP_CEIL, ca.OP_ERF,
         ca.OP_LOG1P, ca.OP_EXPM1}


@dataclass(frozen=True)
class Substitute:
    """What stands in for a branching function: ``function`` (one branch, of the same inputs, or of
    the inputs after the first when ``drops_first``: a ``Function.conditional``'s index), and
    ``condition(operands)``, the SX that is nonzero when the C would take another branch
    (``operands``: the call's inputs, each a list of its nonzeros)."""

    function: ca.Function
    condition: Callable[[list], ca.SX]
    drops_first: bool = False


class Flattener:
    """Re-plays functions with ``substitutes`` (by name); ``conditions`` collects the branch
    conditions met on the way."""

    def __init__(self, substitutes: dict[str, Substitute]):
        self.substitutes, self.conditions = substitutes, []

    def flat(self, fn: ca.Function, inputs: list[list[ca.SX]]) -> list[list[ca.SX]]:
        """The nonzeros of ``fn``'s outputs as SX expressions of ``inputs`` (each input's nonzeros)."""
        if fn.name() in self.substitutes:
            substitute = self.substitutes[fn.name()]
            self.conditions.append(substitute.condition(inputs))
            return self.flat(substitute.function, inputs[1:] if substitute.drops_first else inputs)
        if fn.is_a("MXFunction"):
            return self._replay_mx(fn, inputs)
        if not fn.is_a("SXFunction"):
            raise NotImplementedError(f"lockstep: {fn.name()} is a {fn.class_name()} without a substitute")
        return self._replay_sx(fn, inputs)

    def _replay_sx(self, fn: ca.Function, inputs: list[list[ca.SX]]) -> list[list[ca.SX]]:
        work: dict[int, ca.SX] = {}
        outputs = [[ca.SX(0)] * fn.nnz_out(i) for i in range(fn.n_out())]
        for k in range(fn.n_instructions()):
            op, args, out = fn.instruction_id(k), fn.instruction_input(k), fn.instruction_output(k)
            if op == ca.OP_INPUT:
                work[out[0]] = inputs[args[0]][args[1]]
            elif op == ca.OP_OUTPUT:
                outputs[out[0]][out[1]] = work[args[0]]
            elif op == ca.OP_CONST:
                work[out[0]] = ca.SX(fn.instruction_constant(k))
            elif op == ca.OP_CALL:
                callee = _callee(fn)
                results = self.flat(callee, _grouped(callee, [work[a] for a in args]))
                for slot, value in zip(out, [v for values in results for v in values]):
                    work[slot] = value
            else:
                work[out[0]] = _operation(op, [work[a] for a in args], fn.name())
        return outputs

    def _replay_mx(self, fn: ca.Function, inputs: list[list[ca.SX]]) -> list[list[ca.SX]]:
        """An MX function of calls and elementwise operations (a dispatcher), re-played on SX."""
        work: dict[int, ca.SX] = {}
        outputs = [[] for _ in range(fn.n_out())]
        for k in range(fn.n_instructions()):
            op, args, out = fn.instruction_id(k), fn.instruction_input(k), fn.instruction_output(k)
            if op == ca.OP_INPUT:
                work[out[0]] = _matrix(fn.sparsity_in(args[0]), inputs[args[0]])
            elif op == ca.OP_OUTPUT:
                outputs[out[0]] = _nonzeros(work[args[0]])
            elif op == ca.OP_CONST:
                work[out[0]] = ca.SX(ca.evalf(fn.instruction_MX(k)))
            elif op == ca.OP_CALL:
                callee = fn.instruction_MX(k).which_function()
                results = self.flat(callee, [_nonzeros(work[a]) for a in args])
                for i, (slot, values) in enumerate(zip(out, results)):
                    work[slot] = _matrix(callee.sparsity_out(i), values)
            else:
                work[out[0]] = _operation(op, [work[a] for a in args], fn.name())
        return outputs


def _operation(op: int, operands: list, where: str):
    if op in BINARY:
        return ca.SX.binary(op, operands[0], operands[1])
    if op in UNARY:
        return ca.SX.unary(op, operands[0])
    raise NotImplementedError(f"lockstep: CasADi operation {op} in {where} is not re-played")


def _callee(fn: ca.Function) -> ca.Function:
    """The one function ``fn`` calls (an SX algorithm names its calls only by their order)."""
    called = fn.get_function()
    if len(called) != 1:
        raise NotImplementedError(f"lockstep: {fn.name()} calls {len(called)} functions; one is supported")
    return fn.get_function(called[0])


def _grouped(callee: ca.Function, operands: list) -> list[list]:
    """A call's operands (its inputs' nonzeros in order) split by the callee's inputs."""
    grouped, at = [], 0
    for i in range(callee.n_in()):
        grouped.append(operands[at:at + callee.nnz_in(i)])
        at += callee.nnz_in(i)
    return grouped


def _nonzeros(matrix: ca.SX) -> list:
    return [matrix.nz[i] for i in range(matrix.nnz())]


def _matrix(sparsity: ca.Sparsity, values: list) -> ca.SX:
    return ca.SX(sparsity, ca.vertcat(*values)) if values else ca.SX(sparsity)

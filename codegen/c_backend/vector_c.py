"""An SX Function as C over GCC vector types: :data:`WIDTH` independent evaluations per instruction.

Each CasADi operation becomes the same IEEE operation on a vector of :data:`WIDTH` doubles (AVX2:
``+ - * /`` lane by lane, exact as the scalar ones), a comparison a lane mask turned into 1.0 or
0.0, ``a ? b : 0`` a bitwise select. Every library function (sin, cos, exp, atan2, sqrt, fmin, ...)
is the scalar libm call on each lane, so a lane computes what CasADi's scalar C computes, bit for
bit (the unit is compiled without FMA contraction: AVX2 only, ``-ffp-contract=off``). With
``vector_math``, sin, cos, exp, log, pow and atan2 are instead one call of glibc's libmvec for all
lanes (its AVX2 clones ``_ZGVdN4v_*``): a few ulp from libm a call (glibc documents at most 4),
at a fraction of its cost.
"""
from __future__ import annotations

import math
import platform

import casadi as ca

#: Lanes per vector: AVX2's four doubles.
WIDTH = 4

#: The vector types and helpers the generated functions use (GCC and clang vector extensions).
PRELUDE = f"""typedef double symkf_v4 __attribute__((vector_size({8 * WIDTH})));
typedef long long symkf_m4 __attribute__((vector_size({8 * WIDTH})));
#define SYMKF_SPLAT(c) ((symkf_v4){{{', '.join(['(c)'] * WIDTH)}}})
#define SYMKF_TRUTH(m) ((symkf_v4)((symkf_m4)(m) & (symkf_m4)SYMKF_SPLAT(1.)))
#define SYMKF_NONZERO(a) ((symkf_m4)((a) != SYMKF_SPLAT(0.)))
#define SYMKF_LANE1(f, a) ((symkf_v4){{{', '.join(f'f((a)[{i}])' for i in range(WIDTH))}}})
#define SYMKF_LANE2(f, a, b) ((symkf_v4){{{', '.join(f'f((a)[{i}], (b)[{i}])' for i in range(WIDTH))}}})
__attribute__((unused)) static double symkf_sign(double x) {{ return x < 0 ? -1. : (x > 0 ? 1. : x); }}   /* CasADi's casadi_sign */
"""

_ARITHMETIC = {ca.OP_ADD: "({a}+{b})", ca.OP_SUB: "({a}-{b})", ca.OP_MUL: "({a}*{b})", ca.OP_DIV: "({a}/{b})",
               ca.OP_LT: "SYMKF_TRUTH({a}<{b})", ca.OP_LE: "SYMKF_TRUTH({a}<={b})",
               ca.OP_EQ: "SYMKF_TRUTH({a}=={b})", ca.OP_NE: "SYMKF_TRUTH({a}!={b})",
               ca.OP_AND: "SYMKF_TRUTH(SYMKF_NONZERO({a}) & SYMKF_NONZERO({b}))",
               ca.OP_OR: "SYMKF_TRUTH(SYMKF_NONZERO({a}) | SYMKF_NONZERO({b}))",
               ca.OP_IF_ELSE_ZERO: "((symkf_v4)(SYMKF_NONZERO({a}) & (symkf_m4){b}))"}
_BINARY_CALLS = {ca.OP_POW: "pow", ca.OP_CONSTPOW: "pow", ca.OP_ATAN2: "atan2", ca.OP_FMIN: "fmin",
                 ca.OP_FMAX: "fmax", ca.OP_FMOD: "fmod", ca.OP_COPYSIGN: "copysign", ca.OP_HYPOT: "hypot"}
_UNARY = {ca.OP_ASSIGN: "{a}", ca.OP_NEG: "(-{a})", ca.OP_SQ: "({a}*{a})", ca.OP_TWICE: "(SYMKF_SPLAT(2.)*{a})",
          ca.OP_INV: "(SYMKF_SPLAT(1.)/{a})", ca.OP_NOT: "SYMKF_TRUTH({a}==SYMKF_SPLAT(0.))",
          ca.OP_SIGN: "SYMKF_LANE1(symkf_sign, {a})"}
#: libm functions with an AVX2 clone in glibc's libmvec (since glibc 2.22; atan2 since 2.35): name -> arity.
VECTOR_MATH = {"sin": 1, "cos": 1, "exp": 1, "log": 1, "pow": 2, "atan2": 2}
#: Their declarations (the vector ABI's mangled names: 4 lanes of AVX2, each argument a vector).
VECTOR_MATH_DECLARATIONS = "\n".join(
    f"symkf_v4 _ZGVdN4{'v' * arity}_{name}({', '.join(['symkf_v4'] * arity)});   /* libmvec */"
    for name, arity in VECTOR_MATH.items())
_UNARY_CALLS = {getattr(ca, f"OP_{name.upper()}"): name for name in
                ("exp", "log", "sqrt", "sin", "cos", "tan", "asin", "acos", "atan", "sinh", "cosh", "tanh", "asinh",
                 "acosh", "atanh", "fabs", "floor", "ceil", "erf", "log1p", "expm1")}


def vector_build(config) -> bool:
    """A build whose host library can have AVX2 vector units: double precision on an x86-64 host."""
    return config.precision == "double" and platform.machine() in ("x86_64", "AMD64")


#: The glibc that has every AVX2 clone of :data:`VECTOR_MATH` (atan2's since 2.35).
LIBMVEC_GLIBC = (2, 35)


def libmvec_build(config) -> bool:
    """A vector build whose host links glibc's libmvec (Linux with glibc >= :data:`LIBMVEC_GLIBC`;
    elsewhere, macOS or musl, an option that asks for libmvec leaves libm's calls lane by lane)."""
    libc, version = platform.libc_ver()
    try:
        release = tuple(int(part) for part in version.split(".")[:2])
    except ValueError:
        release = ()
    return vector_build(config) and platform.system() == "Linux" and libc == "glibc" and release >= LIBMVEC_GLIBC


def _literal(value: float) -> str:
    if math.isnan(value):
        return "SYMKF_SPLAT(NAN)"
    if math.isinf(value):
        return f"SYMKF_SPLAT({'' if value > 0 else '-'}HUGE_VAL)"
    return f"SYMKF_SPLAT({float(value)!r})"


def _call(name: str, operands: list[str], vector_math: bool) -> str:
    """A library call on every lane: libmvec's clone (``vector_math``) or libm's function lane by lane."""
    if vector_math and name in VECTOR_MATH:
        return f"_ZGVdN4{'v' * len(operands)}_{name}({', '.join(operands)})"
    return f"SYMKF_LANE{len(operands)}({name}, {', '.join(operands)})"


def _expression(fn: ca.Function, k: int, names: dict[int, str], vector_math: bool) -> str:
    op, args = fn.instruction_id(k), fn.instruction_input(k)
    if op == ca.OP_INPUT:
        return f"in[{args[0]}][{args[1]}]"
    if op == ca.OP_CONST:
        return _literal(fn.instruction_constant(k))
    if op in _ARITHMETIC:
        return _ARITHMETIC[op].format(a=names[args[0]], b=names[args[1]])
    if op in _BINARY_CALLS:
        return _call(_BINARY_CALLS[op], [names[args[0]], names[args[1]]], vector_math)
    if op in _UNARY:
        return _UNARY[op].format(a=names[args[0]])
    if op in _UNARY_CALLS:
        return _call(_UNARY_CALLS[op], [names[args[0]]], vector_math)
    raise NotImplementedError(f"vector C: CasADi operation {op} has no form here")


def vector_body(fn: ca.Function, vector_math: bool = False) -> list[str]:
    """``fn``'s algorithm as C statements on ``const symkf_v4 *const *in`` and ``symkf_v4 *const *out``
    (input i's nonzero j is ``in[i][j]``; output i's nonzero j is written to ``out[i][j]``); with
    ``vector_math``, libmvec's calls for the functions of :data:`VECTOR_MATH`."""
    names: dict[int, str] = {}
    lines = []
    for k in range(fn.n_instructions()):
        op, args, out = fn.instruction_id(k), fn.instruction_input(k), fn.instruction_output(k)
        if op == ca.OP_OUTPUT:
            lines.append(f"out[{out[0]}][{out[1]}] = {names[args[0]]};")
            continue
        lines.append(f"const symkf_v4 w{k} = {_expression(fn, k, names, vector_math)};")
        names[out[0]] = f"w{k}"
    return lines


def writable(fn: ca.Function) -> bool:
    """Every operation of ``fn`` has a vector form here."""
    try:
        vector_body(fn)
    except NotImplementedError:
        return False
    return True

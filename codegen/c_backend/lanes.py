"""Lane-vectorized sigma-point propagation for the host library (the flight bundle stays scalar C99).

A UKF propagates its 2n + 1 sigma points (paper 004, eq (1)-(3)) through one f_d. CasADi's unit
of ``<prefix>_fd_sigma_plain`` (the step without an event) evaluates the points one after another
with scalar libm calls: 58 % of the launcher's UKF step is sincos. This unit evaluates f_d of
:data:`LANES` points per SIMD instruction: f_d's SX algorithm for one point is written out once as
the body of a loop over the points (``#pragma omp simd``, GCC's ``-fopenmp-simd``), its sin, cos,
exp, log, pow and atan2 calls mapped to glibc's libmvec (the AVX2 clones ``_ZGVdN4v_*``), the terms
that depend on t, dt, u and p only evaluated once before the loop, conditionals as lane selects.
The update's h at the sigma points (eq (2)'s predicted measurements) likewise, with
``ukf_lanes_update`` only: its round-off (positions formed at the Earth's radius from libmvec's
sin/cos) moved a campaign run's whole-flight RMS by up to 9.6e-5 relative, the predict's lanes by
at most 1.0e-7 (scenarios/launcher/roundoff_equivalence.py).

Every other operation is CasADi's own (the same IEEE operations in the same order; ``-std=c99``
keeps contraction into FMA off), so a propagated point differs from the scalar unit's only by
libmvec's round-off (glibc: at most 4 ulp a call, where libm is correctly rounded or nearly so).

How it is reached: the scalar unit keeps its code and starts with a call of this unit's function
under ``#ifdef SYMKF_LANES``; that function returns 0 (the scalar code runs) unless the CPU has
AVX2 (``__builtin_cpu_supports``). Only the library's compile defines SYMKF_LANES
(:func:`host_flags`): the bundle's Makefile compiles the scalar code alone and this unit to an
empty one. Lanes are an option (``ukf_lanes=True``; off by default, so that the library computes
what the bundle computes: their round-off can move a chaotic run, docs/performance.md); a single
precision build or a CPU other than x86-64 has none.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import casadi as ca

from ..discretize import measurement_function
from .vector_c import VECTOR_MATH, libmvec_build

#: Points per SIMD instruction: AVX2's four doubles (valgrind counts AVX2, not AVX-512).
LANES = 4
#: Flags of the lanes unit in the library: vectorize at -O3, libmvec through ``omp declare simd``,
#: and sin and cos not merged into scalar sincos calls before the vectorizer sees them.
UNIT_FLAGS = ["-DSYMKF_LANES", "-O3", "-fopenmp-simd", "-fno-builtin-sin", "-fno-builtin-cos"]

#: How the units that call the lanes end (a model with events: the plain branch; without: the function).
HOOKED_UNITS = ("_fd_sigma.c", "_fd_sigma_plain.c", "_fd_sigma_centre_free.c", "_fd_sigma_centre_free_plain.c",
                "_at_sigma.c")

_BINARY = {ca.OP_ADD: "({a}+{b})", ca.OP_SUB: "({a}-{b})", ca.OP_MUL: "({a}*{b})", ca.OP_DIV: "({a}/{b})",
           ca.OP_POW: "pow({a},{b})", ca.OP_CONSTPOW: "pow({a},{b})", ca.OP_LT: "({a}<{b})",
           ca.OP_LE: "({a}<={b})", ca.OP_EQ: "({a}=={b})", ca.OP_NE: "({a}!={b})", ca.OP_AND: "({a}&&{b})",
           ca.OP_OR: "({a}||{b})", ca.OP_IF_ELSE_ZERO: "({a}?{b}:0)", ca.OP_ATAN2: "atan2({a},{b})",
           ca.OP_FMIN: "fmin({a},{b})", ca.OP_FMAX: "fmax({a},{b})", ca.OP_FMOD: "fmod({a},{b})",
           ca.OP_COPYSIGN: "copysign({a},{b})", ca.OP_HYPOT: "hypot({a},{b})"}
_UNARY = {ca.OP_ASSIGN: "{a}", ca.OP_NEG: "(-{a})", ca.OP_SQ: "({a}*{a})", ca.OP_TWICE: "(2.*{a})",
          ca.OP_INV: "(1./{a})", ca.OP_NOT: "(!{a})", ca.OP_SIGN: "({a}<0?-1.:({a}>0?1.:{a}))",
          **{getattr(ca, f"OP_{name.upper()}"): f"{name}({{a}})" for name in
             ("exp", "log", "sqrt", "sin", "cos", "tan", "asin", "acos", "atan", "sinh", "cosh", "tanh", "asinh",
              "acosh", "atanh", "fabs", "floor", "ceil", "erf", "log1p", "expm1")}}


@dataclass(frozen=True)
class LaneSpec:
    """One scalar unit the lanes stand in for: ``symbol``, a function of the sigma points of x and a
    lower-triangular L (x, x + L_i, x - L_i: ``<model>_fn_..._fd_sigma[_centre_free]_plain`` of
    arguments (t, dt, x, L, u, p), or ``<model>_fn_h_<name>_at_sigma`` of (t, x, L, u, p, q)) with
    one column of its output per point; ``point``, that function of one point (SX): its input
    ``varying`` is the point, and ``uniform`` maps each other input to the unit's argument."""

    symbol: str
    point: ca.Function
    centre_free: bool
    varying: int
    x_arg: int
    uniform: tuple[tuple[int, int], ...]

    @property
    def lane_symbol(self) -> str:
        return self.symbol.replace("_fn_", "_lanes_", 1)


def enabled(config) -> bool:
    """Lanes for this configuration: ``ukf_lanes`` (default off), double precision, an x86-64 host
    with glibc's libmvec."""
    return bool(config.get("ukf_lanes", False)) and libmvec_build(config)


def lanes_file(model: str) -> str:
    return f"{model}_lanes.c"


def host_flags(config, unit: str, model: str = "") -> list[str]:
    """The library's extra flags of ``unit`` (none in the bundle's Makefile): the lanes unit's, and
    -DSYMKF_LANES for the scalar units that call it."""
    if not enabled(config) or not unit:
        return []
    if unit.endswith("_lanes.c"):
        return list(UNIT_FLAGS)
    return ["-DSYMKF_LANES"] if unit.endswith(HOOKED_UNITS) else []


def hook(text: str, spec: LaneSpec) -> str:
    """The scalar unit's text with the call of the lanes first (compiled only with SYMKF_LANES)."""
    head = (f"SYMKF_INTERNAL int {spec.symbol}(const casadi_real** arg, casadi_real** res, casadi_int* iw, "
            f"casadi_real* w, int mem) {{\n")
    if head not in text:
        raise ValueError(f"lanes: no definition of {spec.symbol} in its unit")
    declaration = (f"#ifdef SYMKF_LANES\nSYMKF_INTERNAL int {spec.lane_symbol}(const casadi_real** arg, "
                   f"casadi_real** res);   /* in {lanes_file(spec.symbol.split('_fn_')[0])}: 4 points per "
                   f"instruction on an AVX2 CPU */\n#endif\n")
    call = f"#ifdef SYMKF_LANES\n  if ({spec.lane_symbol}(arg, res)) return 0;\n#endif\n"
    at = text.index(head)
    return text[:at] + declaration + head + call + text[at + len(head):]


# ---------------------------------------------------------------------- f_d of one point as C
def specs_of(functions, config) -> tuple[LaneSpec, ...]:
    """The lanes of a UKF's functions (codegen/model_functions.py): f_d at the sigma points (all,
    or the centre-free ones) and each measurement's h at the sigma points; () if lanes are off."""
    if not enabled(config):
        return ()
    propagation = functions.for_filter("ukf")
    branches = propagation.branches
    model = branches.model
    t, dt, x = model.t, ca.SX.sym("dt"), ca.SX.sym("x", model.nx)
    u, p = ca.SX.sym("u", len(model.inputs)), ca.SX.sym("p", len(model.params))
    point = ca.Function("point", [t, dt, x, u, p], [branches.branches[0](t, dt, x, u, p, ca.DM.zeros(len(model.noises)))],
                        {"cse": True})
    plain = "_plain" if len(branches.branches) > 1 else ""
    made = []
    for key in propagation.point_functions:
        if key in (("sigma", False), ("sigma_centre_free", True)):
            name = f"{propagation.prefix}_fd_{key[0]}{plain}"
            made.append(LaneSpec(f"{model.name}_fn_{name[len(model.name) + 1:]}", point, key[1], 2, 2,
                                 ((0, 0), (1, 1), (3, 4), (4, 5))))
    for function in functions.point_h_functions() if config.get("ukf_lanes_update", False) else ():
        h = measurement_function(model, function.name()[len(model.name) + 3:-len("_at_sigma")])
        h = ca.Function("h", h.sx_in(), h.call(h.sx_in()), {"cse": True})
        made.append(LaneSpec(f"{model.name}_fn_{function.name()[len(model.name) + 1:]}", h, False, 1, 1,
                             ((0, 0), (2, 3), (3, 4), (4, 5))))
    return tuple(spec for spec in made if _writable(spec.point))


def _writable(fn: ca.Function) -> bool:
    """Every operation of ``fn`` has a C form here (else its scalar unit runs alone: no lanes)."""
    try:
        point_code(fn, 0)
    except NotImplementedError:
        return False
    return True


def _literal(value: float) -> str:
    if math.isnan(value):
        return "NAN"
    if math.isinf(value):
        return "HUGE_VAL" if value > 0 else "(-HUGE_VAL)"
    return repr(float(value))


def point_code(fn: ca.Function, varying: int) -> tuple[list[str], list[str], list[str]]:
    """f_d of one point as C statements: (uniform, lane, outputs). Input ``varying`` (the state)
    is read as ``xs[k][l]`` in lane l; every other input as ``in[i][k]``. An instruction whose
    inputs are all uniform is uniform (``u<k>``, before the loop), else a lane value (``v<k>``);
    outputs are written to ``ys[k][l]``."""
    names: dict[int, str] = {}
    is_lane: dict[int, bool] = {}
    uniform, lane, outputs = [], [], []
    for k in range(fn.n_instructions()):
        op, args, out = fn.instruction_id(k), fn.instruction_input(k), fn.instruction_output(k)
        if op == ca.OP_OUTPUT:
            outputs.append(f"ys[{out[1]}][l] = {names[args[0]]};")
            continue
        if op == ca.OP_INPUT:
            lane_value = args[0] == varying
            expr = f"xs[{args[1]}][l]" if lane_value else f"in[{args[0]}][{args[1]}]"
        elif op == ca.OP_CONST:
            lane_value, expr = False, _literal(fn.instruction_constant(k))
        elif op in _UNARY:
            lane_value, expr = is_lane[args[0]], _UNARY[op].format(a=names[args[0]])
        elif op in _BINARY:
            lane_value = is_lane[args[0]] or is_lane[args[1]]
            expr = _BINARY[op].format(a=names[args[0]], b=names[args[1]])
        else:
            raise NotImplementedError(f"lanes: CasADi operation {op} has no C form here")
        name = f"{'v' if lane_value else 'u'}{k}"
        (lane if lane_value else uniform).append(f"{'double ' if lane_value else ''}{name} = {expr};")
        names[out[0]], is_lane[out[0]] = name, lane_value
    return uniform, lane, outputs


def _padded(count: int) -> int:
    return -(-count // LANES) * LANES


def lane_function(spec: LaneSpec) -> str:
    """The C of one spec: the AVX2 loop over the points and the entry point that forms the points
    from x and L (as the scalar unit does: x_k + L_ki, x_k - L_ki for k >= i, x_k above) and
    writes the columns of its output; it returns 0 without AVX2 (the caller's scalar code runs)."""
    fn, n = spec.point, spec.point.size1_in(spec.varying)
    m = fn.nnz_out(0)
    first = 1 if spec.centre_free else 0
    points = 2 * n + 1 - first
    pad = _padded(points)
    uniform, lane, outputs = point_code(fn, spec.varying)
    declared = [line.split(" = ")[0] for line in uniform]
    name = spec.lane_symbol
    inputs = "".join(f"  in[{i}] = arg[{j}] ? arg[{j}] : zeros;\n" for i, j in spec.uniform)
    body = [
        f"/* {fn.name()} of {points} points in lanes of {LANES} ({pad} with the padding: copies of x) */",
        f"__attribute__((target(\"avx2\"))) static void {name}_avx2(const double* const* in, "
        f"double (*xs)[{pad}], double (*ys)[{pad}]) {{",
        *([f"  double {', '.join(declared)};"] if declared else []),
        "  int l;",
        "  (void)in;       /* (a function of the point alone reads no other input) */",
        *(f"  {line}" for line in uniform),
        "#pragma omp simd",
        f"  for (l = 0; l < {pad}; ++l) {{",
        *(f"    {line}" for line in lane + outputs),
        "  }",
        "}",
        "",
        f"SYMKF_INTERNAL int {name}(const double** arg, double** res) {{",
        f"  static const double zeros[{max(fn.nnz_in(i) for i in range(fn.n_in())) + n * n}] = {{0.}};",
        f"  double xs[{n}][{pad}], ys[{m}][{pad}];",
        f"  const double* in[{fn.n_in()}];",
        "  const double *x, *L;",
        "  int c, k, i, offset;",
        "  if (!__builtin_cpu_supports(\"avx2\")) return 0;",
        f"  in[{spec.varying}] = zeros;",
        inputs.rstrip("\n"),
        f"  x = arg[{spec.x_arg}] ? arg[{spec.x_arg}] : zeros; L = arg[{spec.x_arg + 1}] ? arg[{spec.x_arg + 1}] : zeros;",
        f"  for (c = 0; c < {pad}; ++c) for (k = 0; k < {n}; ++k) xs[k][c] = x[k];",
        f"  for (c = {max(first, 1)}; c <= {2 * n}; ++c) {{      /* column c: x + L_i (c <= n) or x - L_i */",
        f"    i = c <= {n} ? c - 1 : c - {n + 1};",
        f"    offset = i * {n} - i * (i - 1) / 2;        /* L_ki (k >= i) in L's lower-triangular columns */",
        f"    for (k = i; k < {n}; ++k) xs[k][c - {first}] = c <= {n} ? x[k] + L[offset + k - i] : "
        f"x[k] - L[offset + k - i];",
        "  }",
        f"  {name}_avx2(in, xs, ys);",
        "  if (!res[0]) return 1;",
        *([f"  for (k = 0; k < {n}; ++k) res[0][k] = x[k];      /* the centre (weight 0) as it is */"]
          if spec.centre_free else []),
        f"  for (c = {first}; c <= {2 * n}; ++c) for (k = 0; k < {m}; ++k) res[0][k + {m} * c] = ys[k][c - {first}];",
        "  return 1;",
        "}",
    ]
    return "\n".join(body)


def lanes_unit(model: str, specs: list[LaneSpec], notice: str) -> str:
    """The lanes unit of a bundle: every spec's function, compiled only with SYMKF_LANES."""
    declarations = [line for fn, arity in VECTOR_MATH.items()          # declared simd: the vectorizer calls the clones
                    for line in ("#pragma omp declare simd notinbranch", f"double {fn}({', '.join(['double'] * arity)});")]
    return "\n".join([
        f"/* {notice}", " * Sigma points propagated in SIMD lanes, for the host library only (codegen/c_backend/lanes.py):",
        " * compiled to nothing without SYMKF_LANES (the flight bundle's Makefile). */",
        "#include <math.h>", "",
        f"typedef int {model}_lanes_unit;       /* (a unit is never empty: ISO C) */", "",
        "#if defined(SYMKF_LANES) && defined(__GNUC__) && defined(__x86_64__)",
        "#ifndef SYMKF_INTERNAL", "#define SYMKF_INTERNAL __attribute__((visibility(\"hidden\")))", "#endif", "",
        "/* glibc's libmvec: the vectorizer calls _ZGVdN4v_<name> for 4 lanes */", *declarations, "",
        *[lane_function(spec) + "\n" for spec in specs],
        "#endif", ""])

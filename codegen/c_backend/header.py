"""``<model>.h``, the flight bundle's self-contained header, and the documentation in it.

Its conventions (``templates/header_conventions.h``), the return codes (:func:`status_codes`: those
each kernel can return, read from its expression), dimensions, indices, defaults and scaling of the
model, the model file's constants, then each kernel's prototypes with its time rule, arguments
(unit and meaning), return codes and stack figures (placeholders until
:func:`~symkf.codegen.c_backend.stack.fill_stack`). A float build's precision lines
(:func:`precision_lines`) open the header and every unit.
"""
from __future__ import annotations

import re

import casadi as ca

from ..spec import STATUS_CODES, STATUS_GATED, STATUS_NONFINITE, Arg, Bundle, Kernel
from .api import param_list, passing, run_params, trusted_kernels
from .arguments import diagnosed
from .names import ascii_text, generated_notice
from .multi_loop import multi_doc, multi_filters, multi_params
from .smooth_loop import smooth_doc, smooth_params
from .stack import STACK_PLACEHOLDER
from .template_util import template_text


def _macro(name: str) -> str:
    return re.sub(r"\W", "_", name).upper()


def _number(value) -> str:
    return repr(float(value))


def _time_doc(kernel: Kernel) -> list[str]:
    """Which instant each time argument means, stated per kind of function."""
    names = {a.name for a in kernel.inputs}
    if kernel.backward:
        return [" * Time: x and P (filtered) and the outputs xs, Ps (smoothed) are the estimate at time t; the inputs",
                " *   xs, Ps are the smoothed estimate at t + dt (the step [t, t + dt] follows this estimate)."]
    if "_step_" in kernel.name and {"t", "dt"} <= names:
        return [" * Time: x and P are the estimate at time t; the measurement z was taken at t + dt.",
                " *   The step predicts from t to t + dt, then updates at t + dt; outputs are at t + dt.",
                " *   Pass the time of the previous estimate as t, NOT the measurement time (that runs",
                " *   the prediction one step late)."]
    if {"t", "dt"} <= names:
        return [" * Time: x (and P) are at time t; the outputs are at t + dt (the step covers [t, t + dt])."]
    if "dt" in names:
        return [" * Time: dt is the step length; the outputs are dt after the input state."]
    if "update" in kernel.name and "t" in names:
        return [" * Time: t is the measurement time; x and P must already be the estimate at t",
                " *   (predicted to it). The outputs are the estimate at t."]
    if "t" in names:
        return [" * Time: t is the instant at which x is given (the equations depend on t)."]
    return [" * Time: no time argument."]


def _output_meaning(kernel: Kernel, a: Arg) -> tuple[str, str]:
    """(unit, meaning) of an output, spelled out where the kernel's declaration is terse."""
    x_units = next((b.unit for b in kernel.inputs if b.name == "x"), "-")
    known = {
        "xdot": (f"d/dt of ({x_units}), i.e. state unit per second",
                 "time derivative dx/dt = f(t, x, u, p) at time t, in the state's order"),
        "F": ("row i, column j: unit of x_i / unit of x_j",
              "state-transition Jacobian d f_d(x) / d x over [t, t + dt], column-major"),
        "H": ("row i, column j: unit of z_i / unit of x_j",
              "measurement Jacobian d h / d x at time t, column-major"),
        "z": (a.unit, "predicted measurement h(t, x, u, p, q)"),
    }
    if a.name in known and (a.unit == "-" or not a.description or a.name == "z"):
        return known[a.name]
    return a.unit, a.description or "-"


def _arg_lines(kernel: Kernel) -> list[str]:
    lines = [" * Inputs:"]
    for a in kernel.inputs:
        how = passing(a, kernel)
        if how == "omit":
            lines.append(f" *   ({a.name}: zero size for this model, not an argument)")
            continue
        shape = "scalar" if how == "value" else f"[{a.shape[0]}x{a.shape[1]}]"
        lines.append(f" *   {a.name:<9}{shape:<8} ({a.unit}) {a.description}")
    lines.append(" * Outputs (written only on SYMKF_OK; may alias the inputs):")
    for a in kernel.outputs[:-1]:
        unit, meaning = _output_meaning(kernel, a)
        lines.append(f" *   {a.name + '_out':<9}{f'[{a.shape[0]}x{a.shape[1]}]':<8} ({unit}) {meaning}")
    return lines


def status_codes(kernel: Kernel) -> list[int]:
    """The SYMKF_ERR_* codes a kernel can return: the failure codes its status output can take
    (read from the expression: constants on the value side of its if-else nodes), plus
    SYMKF_ERR_NONFINITE from the wrapper's output check."""
    f = kernel.function
    if not f.is_a("SXFunction"):
        f = f.expand(f.name(), {"allow_duplicate_io_names": True})
    found, seen, stack = set(), set(), [f.call(f.sx_in())[-1]]
    while stack:
        e = stack.pop()
        if e.is_constant():
            found.add(int(float(e)))
        elif e.element_hash() not in seen:
            seen.add(e.element_hash())
            if e.op() == ca.OP_IF_ELSE_ZERO:
                stack.append(e.dep(1))
            elif e.op() == ca.OP_ADD:
                stack += [e.dep(0), e.dep(1)]
    return sorted((found - {0}) | {STATUS_NONFINITE})


def _returns_line(codes: list[int]) -> str:
    names = [STATUS_CODES[c][0] for c in codes if c != STATUS_GATED]
    gated = " SYMKF_GATED (outputs written: x, P as before the update, y and S as computed);" \
        if STATUS_GATED in codes else ""
    return " * Returns: SYMKF_OK;" + gated + " or " + ", ".join(names) + " (nothing written)."


def _function_doc(model: str, kernel: Kernel, trusted: bool = False) -> list[str]:
    name = f"{model}_{kernel.name}"
    codes = status_codes(kernel)
    lines = ["/**", f" * {name}: {kernel.doc}"] + _time_doc(kernel) + _arg_lines(kernel)
    lines += [_returns_line(codes),
              f" * Stack: {_macro(name)}_STACK_BYTES bytes (worst call path, measured by the compiler).", " */",
              f"#define {_macro(name)}_STACK_BYTES {STACK_PLACEHOLDER.format(name)}",
              f"SYMKF_API int {name}({', '.join(param_list(kernel))});",
              f"/** Binding entry for foreign-function interfaces (the Python runtime): the {len(kernel.inputs)}",
              f" * inputs then {len(kernel.outputs) - 1} outputs above as one pointer array, in that order, scalars",
              " * and zero-size arguments included (as pointers). Same return codes. */",
              f"#define {_macro(name)}_V_STACK_BYTES {STACK_PLACEHOLDER.format(name + '_v')}",
              f"SYMKF_API int {name}_v(casadi_real *const *args);", ""]
    if trusted:
        lines += [f"/** As {name}_v without the test that every input is finite (NaN/Inf in an input is then the",
                  " * caller's error: the results are unspecified and may raise FE_INVALID): for a caller that has",
                  " * tested them, as the symkf Python runtime does before it calls a run's trusted kernel. */",
                  f"#define {_macro(name)}_UNCHECKED_V_STACK_BYTES {STACK_PLACEHOLDER.format(name + '_unchecked_v')}",
                  f"SYMKF_API int {name}_unchecked_v(casadi_real *const *args);", ""]
    if kernel.runnable:
        per_step = [a.name for a in kernel.inputs if a.name in kernel.per_step and a.size]
        lines += ["/**", f" * {name}_run: n_steps calls of {name} in a loop (the flight-software time loop).",
                  f" *   Carried state: {', '.join(kernel.carried)}: initial values in "
                  f"{', '.join(c + '0' for c in kernel.carried)}, the value after",
                  f" *   step k in {', '.join(c + '_hist' for c in kernel.carried)}[k * size ...]; status_hist[k] is step k's code.",
                  f" *   Per-step inputs ({', '.join(per_step)}) hold n_steps consecutive blocks; the",
                  " *   others are constant. " + ("Time: step k covers [t[k], t[k] + dt[k]] and z[k] was taken at"
                                                  " t[k] + dt[k]," if "t" in per_step else ""),
                  " *   " + ("so t[k + 1] = t[k] + dt[k]. " if "t" in per_step else "")
                  + "A failed step keeps the state and the loop goes on.",
                  *([f" *   Once a step has succeeded, the loop calls {model}_{kernel.trusted} instead (or one of its",
                     " *   variants: same results), which leaves out tests of the loop's own state (see its description)."]
                    if kernel.trusted else []),
                  " * Returns: the first SYMKF_ERR_* step code (a gated step is not an error), SYMKF_ERR_ARGS if",
                  " *   n_steps < 0, else SYMKF_OK.",
                  f" * Stack: {_macro(name)}_RUN_STACK_BYTES bytes (worst call path, measured by the compiler).",
                  " */",
                  f"#define {_macro(name)}_RUN_STACK_BYTES {STACK_PLACEHOLDER.format(name + '_run')}",
                  f"SYMKF_API int {name}_run({', '.join(run_params(kernel))});", ""]
    if diagnosed(kernel):
        kept = diagnosed(kernel)
        lines += ["/**", f" * {name}_run_diag: {name}_run that also keeps each step's "
                  + " and ".join(a.name for a in kept) + " (as the step returns them):",
                  " *   " + ", ".join(f"{a.name}_hist[k * {a.size} ...]" for a in kept)
                  + " (n_steps blocks each; a failed step's block is unspecified),",
                  " *   e.g. for the normalised innovation squared y^T S^-1 y of every step.",
                  " * Returns: as _run.",
                  f" * Stack: {_macro(name)}_RUN_DIAG_STACK_BYTES bytes (worst call path, measured by the compiler).",
                  " */",
                  f"#define {_macro(name)}_RUN_DIAG_STACK_BYTES {STACK_PLACEHOLDER.format(name + '_run_diag')}",
                  f"SYMKF_API int {name}_run_diag({', '.join(run_params(kernel, diagnostics=True))});", ""]
    if kernel.backward:
        lines += smooth_doc(model, kernel) + [
            f"#define {_macro(name)}_RUN_STACK_BYTES {STACK_PLACEHOLDER.format(name + '_run')}",
            f"SYMKF_API int {name}_run({', '.join(smooth_params(kernel))});", ""]
    return lines


def _dimension_lines(model: str, desc: dict) -> list[str]:
    """Sizes, state/parameter indices, default parameter values and default noise levels."""
    M = _macro(model)
    lines = ["/* ---- Dimensions ---- */",
             f"#define {M}_NX {len(desc['states'])} /* states */",
             f"#define {M}_NU {len(desc['inputs'])} /* known inputs u */",
             f"#define {M}_NP {len(desc['params'])} /* runtime parameters p */",
             f"#define {M}_NW {len(desc['noises'])} /* process noises w entering the dynamics */"]
    for name, meas in desc["measurements"].items():
        lines.append(f"#define {M}_NZ_{_macro(name)} {len(meas['outputs'])} /* components of measurement '{name}' */")
        lines.append(f"#define {M}_NQ_{_macro(name)} {len(meas['params'])} /* parameters q of measurement '{name}' */")
    lines += ["", "/* ---- State, input and parameter indices (unit: meaning) ---- */"]
    for kind, key in (("X", "states"), ("U", "inputs"), ("P", "params")):
        for i, v in enumerate(desc[key]):
            lines.append(f"#define {M}_{kind}_{_macro(v['name'])} {i} /* {v['unit']}: {v['description']} */")
    if desc["params"]:
        lines += ["", "/* ---- Default parameter values (p), usable as: static const casadi_real p[] = "
                  f"{M}_P_DEFAULT; ---- */"]
        for v in desc["params"]:
            lines.append(f"#define {M}_P_{_macro(v['name'])}_DEFAULT {_number(v['default'])} /* {v['unit']} */")
        lines.append(f"#define {M}_P_DEFAULT {{" + ", ".join(_number(v["default"]) for v in desc["params"]) + "}")
    lines += _scaling_lines(M, desc)
    lines += ["", "/* ---- Default measurement noise (1 sigma per component, in its unit) ---- */"]
    for name, meas in desc["measurements"].items():
        units = ", ".join(o["unit"] for o in meas["outputs"])
        lines.append(f"#define {M}_SIGMA_{_macro(name)} {{" + ", ".join(_number(s) for s in meas["sigma"])
                     + f"}} /* {units} */")
    return lines + [""]


def _scaling_lines(M: str, desc: dict) -> list[str]:
    """The state scaling the model declares (codegen/scaling.py) and whether these kernels use it."""
    info = desc.get("state_scaling")
    if not info:
        return []
    used = info["kernels_use_scaled_state"]
    return ["", "/* ---- State scaling: x = OFFSET + SCALE * x~ per state (scales are powers of two). "
            + ("The filters below carry x~ and P~ = P / (SCALE SCALE^T). ---- */" if used else
               "This build carries the physical x and P (unscaled). ---- */"),
            f"#define {M}_STATE_SCALE {{" + ", ".join(_number(v) for v in info["scale"]) + "}",
            f"#define {M}_STATE_OFFSET {{" + ", ".join(_number(v) for v in info["offset"]) + "}",
            f"#define {M}_SCALED_STATE {int(bool(used))}"]


def _constant_lines(model: str, desc: dict, taken: set[str]) -> list[str]:
    """The model file's named constants (models.get_model records them from the file as executed
    for this build, so they are part of the content hash); a name that would shadow a generated
    macro is left out."""
    constants = [c for c in desc.get("constants", []) if f"{_macro(model)}_{c['name']}" not in taken]
    if not constants:
        return []
    lines = ["/* ---- Constants of the model file (module-level UPPER_CASE numbers as the model uses them;",
             " * sequences are initializers) ---- */"]
    for constant in constants:
        value = constant["value"]
        literal = "{" + ", ".join(_number(v) for v in value) + "}" if isinstance(value, list) else _number(value)
        comment = ascii_text(constant["comment"]).replace("*/", "* /")
        lines.append(f"#define {_macro(model)}_{constant['name']} {literal}" + (f" /* {comment} */" if comment else ""))
    return lines + [""]


def header(bundle: Bundle, content_hash: str, compiler: str = "cc", flags: str = "") -> str:
    """The self-contained header. Stack figures are placeholders until
    :func:`~symkf.codegen.c_backend.stack.fill_stack`."""
    model = bundle.model_name
    guard = f"SYMKF_{_macro(model)}_H"
    desc = bundle.description
    lines = [f"/* {generated_notice(model, bundle.description.get('source', ''))}",
             f" * Model: {desc.get('description', '')}",
             f" * Paper: {desc.get('paper', '')}",
             f" * Content hash: {content_hash}",
             template_text("header_conventions.h").format(model=model, compiler=compiler, flags=flags),
             f"#ifndef {guard}", f"#define {guard}", "", *precision_lines(bundle),
             template_text("real.h"), "", template_text("export.h"), "",
             "/* ---- Return codes ---- */"]
    for code, (name, meaning) in STATUS_CODES.items():
        lines.append(f"#ifndef {name}\n#define {name} {code} /* {meaning} */\n#endif")
    dimensions = _dimension_lines(model, desc)
    taken = {word for line in dimensions for word in re.findall(r"#define (\w+)", line)}
    lines += [""] + dimensions + _constant_lines(model, desc, taken)
    lines += ["#ifdef __cplusplus", 'extern "C" {', "#endif", "",
              "/** The content hash this library was generated with (checked by the Python loader). */",
              f"#define {_macro(model)}_CONTENT_HASH_STACK_BYTES {STACK_PLACEHOLDER.format(model + '_content_hash')}",
              f"SYMKF_API const char *{model}_content_hash(void);", ""]
    trusted = {k.name for k in trusted_kernels(bundle)}
    for kernel in bundle.kernels:
        lines += _function_doc(model, kernel, kernel.name in trusted)
    by_name = {k.name: k for k in bundle.kernels}
    for spec in multi_filters(bundle):
        name = f"{model}_{spec.name}_run_multi"
        lines += multi_doc(model, spec, by_name) + [
            f"#define {_macro(name)}_STACK_BYTES {STACK_PLACEHOLDER.format(name)}",
            f"SYMKF_API int {name}({', '.join(multi_params(spec, by_name))});", ""]
    lines += ["#ifdef __cplusplus", "}", "#endif", f"#endif /* {guard} */", ""]
    return ascii_text("\n".join(lines))


def precision_lines(bundle: Bundle) -> list[str]:
    """A float build (precision="float") is single precision by itself: its header defines SYMKF_FLOAT."""
    if bundle.config.precision != "float":
        return []
    lines = ["/* This bundle was generated for single precision (precision=\"float\"): casadi_real is float."]
    if bundle.config.scaled:
        lines += [" * Its filters carry the SCALED state x~ = (x - offset) / scale and P~ = P / (scale scale^T):",
                  " * see the _STATE_SCALE and _STATE_OFFSET arrays below; z, R, y and S are not scaled."]
    return lines + [" */", "#ifndef SYMKF_FLOAT", "#define SYMKF_FLOAT", "#endif", ""]

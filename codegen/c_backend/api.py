"""``<model>_api.c``, the documented C API over the kernels' entry points, and ``<model>_hash.c``.

How each argument is passed (:func:`passing`, also the Python runtime's rule), the input checks
(NaN/Inf refused before any arithmetic, a masked z sanitised), ``_eval`` (a kernel, or a fused
step's predict then update), the public function and its ``_v`` binding entry, the ``_unchecked``
entries of a run's trusted kernel and the ``_run`` time loops of the filter steps.
"""
from __future__ import annotations

import casadi as ca

from ..spec import Arg, Bundle, Kernel
from .arguments import diagnosed, finite_terms, passing, sanitised_z
from .casadi_text import math_block
from .names import ascii_text, generated_notice, public_names, raw_name
from .multi_loop import multi_filters, multi_loop
from .smooth_loop import smooth_loop
from .template_util import template_text


def param_list(kernel: Kernel) -> list[str]:
    params = []
    for a in kernel.inputs:
        how = passing(a, kernel)
        if how == "value":
            params.append(f"casadi_real {a.name}")
        elif how == "pointer":
            params.append(f"const casadi_real {a.name}[{a.size}]")
    params += [f"casadi_real {a.name}_out[{a.size}]" for a in kernel.outputs[:-1] if a.size]
    return params or ["void"]


#: The API unit's finiteness test of an array, exact and on the bits (no floating-point operation,
#: so no floating-point exception; one OR per entry and one test per array instead of a compare
#: and a branch per entry: compilers vectorise it). A double is NaN or infinite exactly when its
#: 11 exponent bits are all ones (IEEE 754); (bits & EXP) + ONE then carries into the top bit,
#: and for every finite value stays below it.
FINITE_HELPER = template_text("finite.c") + "\n"


def _checks(kernel: Kernel, inputs_finite: bool = True) -> list[str]:
    """Refuse NaN/Inf inputs before any arithmetic (a comparison with NaN inside the kernel would
    raise FE_INVALID). A masked component of z may be NaN: it is replaced by 0 in a copy (z_used),
    so it enters no arithmetic, and the used components are tested there. ``inputs_finite``
    False: the inputs are the caller's to test (an ``_unchecked`` entry), z_used is still made."""
    terms = finite_terms(kernel, [a.name for a in kernel.inputs],
                          lambda a: f"&{a.name}" if passing(a, kernel) == "value" else a.name)
    lines = [f"  if (!({' && '.join(terms or ['1'])})) return SYMKF_ERR_NONFINITE;"] if inputs_finite else []
    if sanitised_z(kernel):
        size = next(a.size for a in kernel.inputs if a.name == "z")
        index = "[i]" if size > 1 else ""           # a one-component z and mask come by value
        lines = [f"  casadi_real z_used[{size}];", "  int i;"] + lines
        lines.append(f"  for (i = 0; i < {size}; ++i) z_used[i] = mask{index} > (casadi_real) 0.5 ? z{index} : (casadi_real) 0;")
        lines.append(f"  if (!symkf_finite(z_used, {size})) return SYMKF_ERR_NONFINITE;")
    return lines


def _arg_expression(a: Arg, kernel: Kernel, replace: dict[str, str]) -> str:
    """What a kernel call's arg[] slot receives for input ``a`` (by name; ``replace`` overrides)."""
    if a.name in replace:
        return replace[a.name]
    return {"omit": "0", "value": f"&{a.name}", "pointer": a.name}[passing(a, kernel)]


def _call_kernel(model: str, kernel: Kernel, outputs: list[str], replace: dict[str, str]) -> list[str]:
    """Fill arg[] and res[] and call a kernel's entry point (status into ``status``)."""
    lines = [f"  arg[{i}] = {_arg_expression(a, kernel, replace)};" for i, a in enumerate(kernel.inputs)]
    lines += [f"  res[{i}] = {name};" for i, name in enumerate(outputs)]
    lines.append(f"  res[{len(kernel.outputs) - 1}] = &status;")
    lines.append(f"  if ({raw_name(model, kernel)}(arg, res, iw, w, 0) != 0) return SYMKF_ERR_EVAL;")
    return lines


def _eval(model: str, kernel: Kernel, kernels: dict[str, Kernel], into: bool = False) -> str:
    """``<model>_<kernel>_eval``: the kernel on inputs already checked. A fused step calls its
    predict, returns predict's code if that failed, then calls its update at t + dt on the
    predicted x and P (the step Function's composition, compose_step, without its copies).

    ``into``: ``<model>_<kernel>_eval_into``, for the run loops: the outputs are written straight
    into the ``*_out`` arrays (no copy through temporaries), which must not overlap the inputs;
    on an error code their contents are unspecified (the loop restores the state)."""
    called = [kernels[name] for name in kernel.parts] or [kernel]
    sizes = [max([getattr(k.function, size)() for k in called] + [1]) for size in ("sz_arg", "sz_res", "sz_iw", "sz_w")]
    suffix = "_eval_into" if into else "_eval"
    lines = [f"static int {model}_{kernel.name}{suffix}({', '.join(param_list(kernel))}) {{",
             f"  const casadi_real *arg[{sizes[0]}];", f"  casadi_real *res[{sizes[1]}];",
             f"  int iw[{sizes[2]}];", f"  casadi_real w[{sizes[3]}];", "  casadi_real status = 0;"]
    lines += [f"  casadi_real tmp{i}[{max(a.size, 1)}];" for i, a in enumerate(kernel.outputs[:-1])
              if not (into and a.size)]
    lines.append("  int i;")
    replace = {}
    if kernel.parts:
        predict = called[0]
        lines += [f"  casadi_real predicted_{a.name}[{max(a.size, 1)}];" for a in predict.outputs[:-1]]
        lines.append("  casadi_real t_next;")
        lines += _call_kernel(model, predict, [f"predicted_{a.name}" for a in predict.outputs[:-1]], {})
        lines += ["  if (status != 0) return (int) status;", "  t_next = t + dt;"]
        replace = {"t": "&t_next", "x": "predicted_x", "P": "predicted_P"}      # as compose_step
    last = called[-1]
    written = [f"{a.name}_out" if into and a.size else f"tmp{i}" for i, a in enumerate(kernel.outputs[:-1])]
    lines += _call_kernel(model, last, written, replace)
    lines.append("  if (status != 0 && status != SYMKF_GATED) return (int) status;   /* gated: written, reported */")
    for where, a in zip(written, kernel.outputs[:-1]):
        if a.size:
            lines.append(f"  if (!symkf_finite({where}, {a.size})) return SYMKF_ERR_NONFINITE;")
    for i, a in enumerate(kernel.outputs[:-1]):
        if a.size and not into:
            lines.append(f"  for (i = 0; i < {a.size}; ++i) {a.name}_out[i] = tmp{i}[i];")
    lines += ["  (void)i;", "  return (int) status;", "}", ""]
    return "\n".join(lines)


def _z_used(kernel: Kernel) -> str:
    """The sanitised z as an ``_eval`` argument (a one-component z is passed by value)."""
    return "z_used" if next(a.size for a in kernel.inputs if a.name == "z") > 1 else "z_used[0]"


def _call_list(kernel: Kernel, value) -> list[str]:
    """The argument list of a call of ``<kernel>_eval``: ``value(a)`` for each input passed, then the outputs."""
    args = [value(a) for a in kernel.inputs if passing(a, kernel) != "omit"]
    return args + [f"{a.name}_out" for a in kernel.outputs[:-1] if a.size]


def _wrapper(model: str, kernel: Kernel, unchecked: bool = False) -> str:
    """The public function (inputs checked, then ``_eval`` of the kernel or of the first of its
    variants whose zero entries are all 0) and its binding entry ``_v``; ``unchecked``: the same
    without the inputs' finiteness test, ``<kernel>_unchecked`` (static) and its ``_unchecked_v``
    (the entry of a run's trusted kernel that the Python runtime calls: :func:`public_functions`)."""
    sanitised = sanitised_z(kernel)
    entry = f"{model}_{kernel.name}" + ("_unchecked" if unchecked else "")
    arguments = "(" + ", ".join(_call_list(kernel, lambda a: _z_used(kernel) if sanitised and a.name == "z" else a.name)) + ");"
    lines = [f"{'static ' if unchecked else ''}int {entry}({', '.join(param_list(kernel))}) {{",
             *_checks(kernel, inputs_finite=not unchecked)]
    for name, conditions in kernel.variants:
        zero = [_zero_test(kernel, input_name, entries, value=True) for input_name, entries in conditions if entries]
        lines.append(f"  if ({' && '.join(zero) or '1'}) return {model}_{name}_eval{arguments}")
    lines += [f"  return {model}_{kernel.name}_eval{arguments}", "}", ""]
    call = []
    for i, a in enumerate(kernel.inputs):
        how = passing(a, kernel)
        if how != "omit":
            call.append(f"*args[{i}]" if how == "value" else f"args[{i}]")
    n_in = len(kernel.inputs)
    call += [f"args[{n_in + i}]" for i, a in enumerate(kernel.outputs[:-1]) if a.size]
    lines += [f"int {entry}_v(casadi_real *const *args) {{", f"  return {entry}({', '.join(call)});", "}", ""]
    return "\n".join(lines)


def trusted_kernels(bundle: Bundle) -> list[Kernel]:
    """The kernels some run loop iterates as its ``trusted`` partner (:class:`~symkf.codegen.spec.Kernel`)."""
    names = {k.trusted for k in bundle.kernels if k.trusted}
    return [k for k in bundle.kernels if k.name in names]


def run_params(kernel: Kernel, diagnostics: bool = False) -> list[str]:
    """The parameters of ``<kernel>_run`` (``diagnostics``: of ``<kernel>_run_diag``, which also
    takes a history of each of :func:`diagnosed`'s outputs)."""
    params = ["int n_steps"]
    for a in kernel.inputs:
        how = passing(a, kernel, run=True)
        if how == "omit":
            continue
        if a.name in kernel.carried:
            params.append(f"const casadi_real {a.name}0[{a.size}]")
        elif a.name in kernel.per_step:
            params.append(f"const casadi_real *{a.name}")
        elif how == "value":
            params.append(f"casadi_real {a.name}")
        else:
            params.append(f"const casadi_real {a.name}[{a.size}]")
    params += [f"casadi_real *{name}_hist" for name in kernel.carried]
    params += [f"casadi_real *{a.name}_hist" for a in diagnosed(kernel)] if diagnostics else []
    params += ["int *status_hist"]
    return params


def _step_argument(a: Arg, kernel: Kernel) -> str | None:
    """The expression a run loop passes to the step function for input ``a`` at step k."""
    how = passing(a, kernel)
    if how == "omit":
        return None
    if a.name in kernel.per_step:
        return f"{a.name}[k]" if how == "value" else f"{a.name} + (long) k * {a.size}"
    return a.name


def _run_address(a: Arg, kernel: Kernel) -> str:
    """The address of input ``a``'s values in a run loop (step k's block of a per-step input)."""
    if a.name in kernel.carried:
        return f"{a.name}0"
    if a.name in kernel.per_step:
        return f"&{a.name}[k]" if a.size == 1 else f"{a.name} + (long) k * {a.size}"
    return f"&{a.name}" if passing(a, kernel) == "value" else a.name


def _run_loop(model: str, kernel: Kernel, kernels: dict[str, Kernel], diagnostics: bool = False) -> str:
    """``<kernel>_run``: the filter's time loop; a failed step keeps the state and records its code.
    ``diagnostics``: ``<kernel>_run_diag``, the same loop writing step k's y and S (:func:`diagnosed`)
    into row k of their histories (a failed step's row is unspecified).

    The inputs that do not change along the run (parameters, noise, the initial state) are checked
    once, the per-step ones (t, dt, z, ...) at each step: a state a step returns is finite (checked
    on output) or the state it was given. The codes are those of step-by-step calls. Each step
    writes its state straight into the history (``_eval_into``), read back as the next step's
    input; a failed step's row is the state it was given. Once a step has succeeded, the loop
    calls the kernel's ``trusted`` partner, if it has one (:class:`~symkf.codegen.spec.Kernel`)."""
    outputs = {a.name: a for a in kernel.outputs}
    sanitised = sanitised_z(kernel)
    trusted = kernels[kernel.trusted] if kernel.trusted else None
    suffix, kept = ("_run_diag", {a.name for a in diagnosed(kernel)}) if diagnostics else ("_run", set())
    lines = [f"int {model}_{kernel.name}{suffix}({', '.join(run_params(kernel, diagnostics))}) {{"]
    for name in kernel.carried:     # a copy: the caller's x0 may be a row of its own x_hist
        lines.append(f"  casadi_real {name}_first[{max(outputs[name].size, 1)}];")
        lines.append(f"  const casadi_real *{name} = {name}_first;")
    for a in kernel.outputs[:-1]:
        if a.name not in kernel.carried and a.size and a.name not in kept:
            lines.append(f"  casadi_real {a.name}_scratch[{a.size}];")
    if sanitised:
        lines.append(f"  casadi_real z_used[{next(a.size for a in kernel.inputs if a.name == 'z')}];")
    fixed = [a.name for a in kernel.inputs if a.name not in kernel.per_step]
    per_step = [a.name for a in kernel.inputs if a.name in kernel.per_step]
    fixed_terms = finite_terms(kernel, fixed, lambda a: _run_address(a, kernel)) or ["1"]
    step_terms = finite_terms(kernel, per_step, lambda a: _run_address(a, kernel)) or ["1"]
    lines += ["  int k, i, code, own = 0, first_error = SYMKF_OK;",
              "  if (n_steps < 0) return SYMKF_ERR_ARGS;",
              f"  const int fixed_finite = {' && '.join(fixed_terms)};"]
    for v, (_, conditions) in enumerate(trusted.variants if trusted else ()):     # conditions on fixed inputs, once
        zero = [_zero_test(kernel, name, entries) for name, entries in conditions if name not in kernel.per_step and entries]
        lines.append(f"  const int variant{v} = {' && '.join(zero) or '1'};")
    for name in kernel.carried:
        lines.append(f"  for (i = 0; i < {outputs[name].size}; ++i) {name}_first[i] = {name}0[i];")
    lines.append("  for (k = 0; k < n_steps; ++k) {")
    for name in kernel.carried:
        size = outputs[name].size
        lines.append(f"    casadi_real *{name}_at = {name}_hist + (long) k * {size};")
    lines.append("    code = SYMKF_ERR_NONFINITE;")
    lines.append(f"    if (fixed_finite && {' && '.join(step_terms)}) {{")

    def argument(a: Arg) -> str:
        if sanitised and a.name == "z":
            return _z_used(kernel)
        return a.name if a.name in kernel.carried else _step_argument(a, kernel)
    call = [argument(a) for a in kernel.inputs if passing(a, kernel) != "omit"]
    call += [f"{a.name}_at" if a.name in kernel.carried else f"{a.name}_hist + (long) k * {a.size}" if a.name in kept
             else f"{a.name}_scratch" for a in kernel.outputs[:-1] if a.size]
    calls = _run_calls(model, kernel, trusted, f"({', '.join(call)});")
    if sanitised:
        size = next(a.size for a in kernel.inputs if a.name == "z")
        mask = next(a for a in kernel.inputs if a.name == "mask")
        z_at = "z[k]" if size == 1 else "z[(long) k * {0} + i]".format(size)
        mask_at = "mask[k]" if size == 1 else "mask[(long) k * {0} + i]".format(mask.size)
        lines.append(f"      for (i = 0; i < {size}; ++i) z_used[i] = {mask_at} > (casadi_real) 0.5 ? {z_at} : (casadi_real) 0;")
        lines.append(f"      if (symkf_finite(z_used, {size})) {{")
        lines += [f"  {line}" for line in calls]
        lines.append("      }")
    else:
        lines += calls
    lines.append("    }")
    lines.append("    status_hist[k] = code;")
    lines.append("    if (code == SYMKF_OK || code == SYMKF_GATED) {")
    lines += [f"      {name} = {name}_at;" for name in kernel.carried]
    lines.append("      own = 1;")
    lines.append("    } else {                     /* the state it was given */")
    for name in kernel.carried:
        lines.append(f"      for (i = 0; i < {outputs[name].size}; ++i) {name}_at[i] = {name}[i];")
    lines.append("      if (first_error == SYMKF_OK) first_error = code;")
    lines.append("    }")
    lines += ["  }", "  (void)own;", "  return first_error;", "}", ""]
    return "\n".join(lines)


def _run_calls(model: str, kernel: Kernel, trusted: Kernel | None, arguments: str) -> list[str]:
    """The run loop's call of step k: the kernel until a step has succeeded, then its trusted
    partner or the first of the partner's variants whose zero entries are all 0 at step k."""
    checked = f"code = {model}_{kernel.name}_eval_into{arguments}"
    if trusted is None:
        return [f"      {checked}"]
    lines = [f"      if (!own) {checked}"]
    for v, (name, conditions) in enumerate(trusted.variants):
        zero = [_zero_test(kernel, input_name, entries, "k") for input_name, entries in conditions
                if input_name in kernel.per_step and entries]
        lines.append(f"      else if ({' && '.join([f'variant{v}'] + zero)}) code = {model}_{name}_eval_into{arguments}")
    lines.append(f"      else code = {model}_{trusted.name}_eval_into{arguments}")
    return lines


def _zero_test(kernel: Kernel, name: str, entries, step: str | None = None, value: bool = False) -> str:
    """C test that the given entries of input ``name`` are exactly 0 (at step ``step`` of a run
    for a per-step input; ``value``: as the public step function takes it)."""
    a = next(a for a in kernel.inputs if a.name == name)
    if step is not None:
        at = [f"{name}[{step}]" if a.size == 1 else f"{name}[(long) {step} * {a.size} + {e}]" for e in entries]
    else:
        by_value = passing(a, kernel, run=not value) == "value"
        at = [name if by_value else f"{name}[{e}]" for e in entries]
    return " && ".join(f"{where} == 0" for where in at) or "1"


def api_unit(bundle: Bundle) -> str:
    """``<model>_api.c``: the documented API (wrappers, binding entries, run loops) over the
    kernels' entry points in their own units. The content hash is not in it (:func:`hash_unit`)."""
    model = bundle.model_name
    prototypes = [f"SYMKF_INTERNAL int {raw_name(model, k)}(const casadi_real **arg, casadi_real **res, int *iw, "
                  "casadi_real *w, int mem);" for k in bundle.kernels]
    by_name = {k.name: k for k in bundle.kernels}
    trusted = {k.name for k in trusted_kernels(bundle)}
    trusted |= {v for k in bundle.kernels if k.name in trusted for v, _ in k.variants}
    functions = [FINITE_HELPER]
    for kernel in bundle.kernels:
        functions.append(_eval(model, kernel, by_name))
        if kernel.runnable or kernel.backward or kernel.name in trusted:
            functions.append(_eval(model, kernel, by_name, into=True))
    functions += [_wrapper(model, kernel) for kernel in bundle.kernels]
    functions += [_wrapper(model, kernel, unchecked=True) for kernel in trusted_kernels(bundle)]
    functions += [_run_loop(model, kernel, by_name) for kernel in bundle.kernels if kernel.runnable]
    functions += [_run_loop(model, kernel, by_name, diagnostics=True) for kernel in bundle.kernels if diagnosed(kernel)]
    functions += [smooth_loop(model, kernel) for kernel in bundle.kernels if kernel.backward]
    functions += [multi_loop(model, spec, by_name) for spec in multi_filters(bundle)]
    parts = [f"/* {generated_notice(model, bundle.description.get('source', ''))}",
             f" * CasADi {ca.__version__}. */",
             "#include <math.h>",
             "#include <stdint.h>",
             "#include <string.h>",
             f'#include "{model}.h"',
             "",
             "/* Explicit double or float math functions (no <tgmath.h>). */",
             math_block("\n".join(functions)),
             template_text("real_check.c"),
             "",
             template_text("internal.h"),    # the entry points' visibility
             "/* The kernels' entry points (CasADi's code, one unit each: <name>.c). */",
             *prototypes,
             "",
             "/* ---------------- symkf wrappers: the public API ---------------- */",
             "", *functions]
    return ascii_text("\n".join(parts))


def hash_unit(model: str, content_hash: str, source: str = "") -> str:
    """``<model>_hash.c``: ``<model>_content_hash()``, alone in its unit (every build changes it)."""
    return "\n".join([f"/* {generated_notice(model, source)}",
                      " * The content hash this library was generated with (checked by the Python loader). */",
                      f'#include "{model}.h"', "",
                      f'const char *{model}_content_hash(void) {{ return "{content_hash}"; }}', ""])


def public_functions(bundle: Bundle) -> list[str]:
    """Every exported symbol of the library, in header order (what ``nm -D`` must list)."""
    names = [f"{bundle.model_name}_content_hash"]
    trusted = {k.name for k in trusted_kernels(bundle)}
    for kernel in bundle.kernels:
        names += public_names(bundle.model_name, kernel, kernel.name in trusted)
    return names + [f"{bundle.model_name}_{spec.name}_run_multi" for spec in multi_filters(bundle)]

"""``<model>_<smoother>_run``: a fixed-interval smoother's backward loop over a forward run.

The smoother kernel (codegen/families/rts.py, ``Kernel.backward = ("xs", "Ps")``) is one backward
step; this loop calls it for k = N-2 .. 0 on the histories a forward ``<step>_run`` wrote (its x_hist,
P_hist and status_hist) and on the run's own per-step t, dt, u: backward step k reads row k of x and
P and step k + 1's t, dt and u (the step that predicted from row k). Row N-1 is the filtered row.

Steps the forward run did not complete: a step k + 1 that failed (a SYMKF_ERR_* code; gated steps
are not failures) kept row k as row k + 1, so the transition between the two rows is the identity
and smoothed row k is smoothed row k + 1. A backward step that fails writes the filtered row k
(smoothing restarts from it), records its code in smooth_status[k] and the loop goes on; the loop
returns the first such code. No heap: the caller provides every history (sizes in the header).
"""
from __future__ import annotations

from ..spec import Kernel
from .arguments import finite_terms, passing

#: Forward-run outputs the backward loop reads as row k (the filtered estimate).
FILTERED = ("x", "P")


def smooth_params(kernel: Kernel) -> list[str]:
    """The C parameters of the backward loop (the forward run's arrays first, then the outputs)."""
    params = ["int n_steps"]
    for a in kernel.inputs:
        how = passing(a, kernel)
        if how == "omit" or a.name in kernel.backward:
            continue
        if a.name in FILTERED:
            params.append(f"const casadi_real *{a.name}_hist")
        elif a.name in kernel.per_step:
            params.append(f"const casadi_real *{a.name}")
        elif how == "value":
            params.append(f"casadi_real {a.name}")
        else:
            params.append(f"const casadi_real {a.name}[{a.size}]")
    params.append("const int *status_hist")
    params += [f"casadi_real *{name}_hist" for name in kernel.backward]
    return params + ["int *smooth_status"]


def _row(a, step: str) -> str:
    """Input ``a`` at row ``step`` of a history or per-step array (its address, or a scalar's value)."""
    name = f"{a.name}_hist" if a.name in FILTERED else a.name
    if a.size == 1 and a.name not in FILTERED:
        return f"{name}[{step}]"
    return f"{name} + (long) ({step}) * {a.size}"


def _address(a, step: str) -> str:
    """The address of input ``a``'s values at row ``step`` (for the finiteness test)."""
    name = f"{a.name}_hist" if a.name in FILTERED else a.name
    return f"{name} + (long) ({step}) * {a.size}"


def smooth_loop(model: str, kernel: Kernel) -> str:
    """The C text of ``<model>_<kernel>_run`` (see the module docstring)."""
    sizes = {a.name: a.size for a in kernel.outputs}
    fixed = [a.name for a in kernel.inputs if a.name not in kernel.per_step and a.name not in kernel.backward]
    fixed_terms = finite_terms(kernel, fixed, lambda a: f"&{a.name}" if passing(a, kernel) == "value" else a.name)
    row = [a.name for a in kernel.inputs if a.name in FILTERED]
    ahead = [a.name for a in kernel.inputs if a.name in kernel.per_step and a.name not in FILTERED]
    step_terms = (finite_terms(kernel, row, lambda a: _address(a, "k"))
                  + finite_terms(kernel, ahead, lambda a: _address(a, "k + 1")))

    def argument(a) -> str:
        if a.name in kernel.backward:
            return f"{a.name}_hist + (long) (k + 1) * {a.size}"
        if a.name in FILTERED:
            return _row(a, "k")
        if a.name in kernel.per_step:
            return _row(a, "k + 1")
        return a.name
    call = [argument(a) for a in kernel.inputs if passing(a, kernel) != "omit"]
    call += [f"{a.name}_hist + (long) k * {a.size}" for a in kernel.outputs[:-1] if a.size]
    copies = [(name, FILTERED[i]) for i, name in enumerate(kernel.backward)]
    lines = [f"int {model}_{kernel.name}_run({', '.join(smooth_params(kernel))}) {{",
             "  int k, code, first_error = SYMKF_OK;",
             "  if (n_steps < 0) return SYMKF_ERR_ARGS;",
             "  if (n_steps == 0) return SYMKF_OK;",
             f"  const int fixed_finite = {' && '.join(fixed_terms or ['1'])};",
             "  code = fixed_finite ? SYMKF_OK : SYMKF_ERR_NONFINITE;"]
    for name, source in copies:          # the last row: smoothed = filtered
        lines.append(_copy(f"{name}_hist", "n_steps - 1", f"{source}_hist", "n_steps - 1", sizes[name], "  "))
    lines += ["  smooth_status[n_steps - 1] = code;", "  first_error = code;",
              "  for (k = n_steps - 2; k >= 0; --k) {",
              "    if (status_hist[k + 1] != SYMKF_OK && status_hist[k + 1] != SYMKF_GATED) {"
              "   /* row k + 1 is row k */"]
    for name, _ in copies:
        lines.append(_copy(f"{name}_hist", "k", f"{name}_hist", "k + 1", sizes[name], "      "))
    lines += ["      code = SYMKF_OK;", "    } else {", "      code = SYMKF_ERR_NONFINITE;",
              f"      if (fixed_finite && {' && '.join(step_terms or ['1'])})",
              f"        code = {model}_{kernel.name}_eval_into({', '.join(call)});",
              "    }",
              "    if (code != SYMKF_OK) {           /* the filtered row k */"]
    for name, source in copies:
        lines.append(_copy(f"{name}_hist", "k", f"{source}_hist", "k", sizes[name], "      "))
    lines += ["      if (first_error == SYMKF_OK) first_error = code;", "    }",
              "    smooth_status[k] = code;", "  }", "  return first_error;", "}", ""]
    return "\n".join(lines)


def _copy(target: str, target_row: str, source: str, source_row: str, size: int, indent: str) -> str:
    """Row ``source_row`` of ``source`` into row ``target_row`` of ``target`` with memcpy: rows
    never overlap, and a loop copying within one array would become a call of memmove, which the
    bundle does not use (it needs only libm, memcpy and memset)."""
    return (f"{indent}memcpy({target} + (long) ({target_row}) * {size}, {source} + (long) ({source_row}) * {size}, "
            f"{size} * sizeof(casadi_real));")


def smooth_doc(model: str, kernel: Kernel) -> list[str]:
    """The header's description of the backward loop, with the sizes of every history."""
    name = f"{model}_{kernel.name}"
    n = next(a.size for a in kernel.inputs if a.name == "x")
    per_step = [a for a in kernel.inputs if a.name in kernel.per_step and a.name not in FILTERED and a.size]
    sizes = ", ".join(f"{a.name}: n_steps * {a.size}" for a in per_step)
    return ["/**", f" * {name}_run: the smoother's backward pass over a forward run of n_steps steps (no heap:",
            " *   the caller provides every array). Inputs: the forward <filter>_step_<m>_run's own per-step",
            f" *   arrays ({sizes}), its histories x_hist (n_steps * {n}),",
            f" *   P_hist (n_steps * {n * n}) and status_hist (n_steps ints), and the constants it ran with.",
            f" *   Outputs: xs_hist (n_steps * {n}), Ps_hist (n_steps * {n * n}), smooth_status (n_steps ints).",
            f" *   Backward step k (k = n_steps-2 .. 0) calls {name} on row k of x_hist and P_hist with",
            " *   t, dt, u of step k + 1; row n_steps-1 is the filtered row. A step k + 1 that failed",
            " *   (SYMKF_ERR_*; gated is not a failure) left row k + 1 = row k: smoothed row k is row k + 1's.",
            " *   A backward step that fails writes the filtered row k and records its code.",
            " * Returns: the first SYMKF_ERR_* code of smooth_status, SYMKF_ERR_ARGS if n_steps < 0, else SYMKF_OK.",
            f" * Stack: {_macro(name)}_RUN_STACK_BYTES bytes (worst call path, measured by the compiler).", " */"]


def _macro(name: str) -> str:
    return name.upper()

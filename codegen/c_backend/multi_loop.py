"""``<model>_<filter>_run_multi``: one time loop over a record of several measurements.

Each step k predicts from t[k] over dt[k] (the filter's predict kernel), then updates, in the
model's measurement order, with every measurement present at step k (one whose mask has an entry
> 0.5; an absent one is skipped, which is what its all-masked update would do: x and P unchanged)
at t[k] + dt[k]: the order a flight loop applies them in. Per step and measurement the caller gives
q, z and mask (n_steps blocks each); R and gate are constant per measurement.

Codes: status_hist[k * (M + 1)] is step k's prediction code, status_hist[k * (M + 1) + 1 + j]
measurement j's update code (SYMKF_OK when absent). A failed prediction keeps the state (the row
is the state it was given) and skips the step's updates (their codes are the prediction's); a
failed update keeps the state it was given and the next measurement updates it. y and S of a
measurement are written to its row k when it updated (other rows are unspecified). Returns the
first SYMKF_ERR_* code (gated is not an error). Generated for a filter with a prediction and
updates for two or more measurements, whose prediction reads no measurement input.
"""
from __future__ import annotations

from ..spec import Bundle, FilterSpec, Kernel
from .arguments import passing, sanitised_z

#: Inputs of an update that belong to its measurement (a suffix ``_<measurement>`` in the loop).
OWN = ("q", "z", "mask", "R", "gate")
#: Measurement inputs given per step; R and gate are constant.
OWN_PER_STEP = ("q", "z", "mask")


def multi_filters(bundle: Bundle) -> list[FilterSpec]:
    """The filters that get a ``_run_multi`` loop."""
    kernels = {k.name: k for k in bundle.kernels}
    return [spec for spec in bundle.filters if spec.predict and len(spec.update) > 1
            and not any(a.name in OWN for a in kernels[spec.predict].inputs)]


def _shared(spec: FilterSpec, kernels: dict[str, Kernel]) -> list:
    """Inputs the prediction and updates share besides t, dt, x, P (u per step; p, Q, kappa fixed)."""
    seen, shared = set(), []
    for kernel in [kernels[spec.predict]] + [kernels[k] for k in spec.update.values()]:
        for a in kernel.inputs:
            if a.name not in seen and a.name not in OWN + ("t", "dt", "x", "P") and a.size:
                seen.add(a.name)
                shared.append(a)
    return shared


def multi_arguments(spec: FilterSpec, kernels) -> list[tuple[str, str, str | None, str, int]]:
    """The parameters of ``_run_multi`` after n_steps, in order, as (C name, input name, measurement
    or None, kind, size); kind: "per_step" (n_steps blocks), "value" (a constant scalar), "array"
    (a constant array), "initial" (x0, P0), "history" (n_steps blocks written) or "status".
    ``kernels``: by name, anything with ``inputs``/``outputs`` of :class:`~symkf.codegen.spec.Arg`
    (the runtime passes the manifest's, in the same order)."""
    sizes = {a.name: a.size for a in kernels[spec.predict].inputs}
    out = [("t", "t", None, "per_step", 1), ("dt", "dt", None, "per_step", 1),
           ("x0", "x", None, "initial", sizes["x"]), ("P0", "P", None, "initial", sizes["P"])]
    for a in _shared(spec, kernels):
        kind = "per_step" if a.name == "u" else "value" if passing(a, None) == "value" else "array"
        out.append((a.name, a.name, None, kind, a.size))
    for m, name in spec.update.items():
        for a in kernels[name].inputs:
            if a.name in OWN and a.size:
                kind = "per_step" if a.name in OWN_PER_STEP else "value" if passing(a, None) == "value" else "array"
                out.append((f"{a.name}_{m}", a.name, m, kind, a.size))
    out += [("x_hist", "x", None, "history", sizes["x"]), ("P_hist", "P", None, "history", sizes["P"])]
    for m, name in spec.update.items():
        out += [(f"{a.name}_{m}_hist", a.name, m, "history", a.size) for a in kernels[name].outputs[:-1]
                if a.name in spec.diagnostics]
    return out + [("status_hist", "status", None, "status", len(spec.update) + 1)]


def multi_params(spec: FilterSpec, kernels: dict[str, Kernel]) -> list[str]:
    """The C parameter list of ``_run_multi``."""
    spelled = {"per_step": "const casadi_real *{0}", "value": "casadi_real {0}", "array": "const casadi_real {0}[{1}]",
               "initial": "const casadi_real {0}[{1}]", "history": "casadi_real *{0}", "status": "int *{0}"}
    return ["int n_steps"] + [spelled[kind].format(c, size) for c, _, _, kind, size in multi_arguments(spec, kernels)]


def _value(a, kernel: Kernel, m: str | None = None) -> str:
    """Input ``a`` of ``kernel`` at step k as its ``_eval`` takes it (by value or by address)."""
    name = f"{a.name}_{m}" if m and a.name in OWN else a.name
    per_step = a.name == "u" or a.name in OWN_PER_STEP
    if not per_step:
        return name
    if passing(a, kernel) == "value":
        return f"{name}[k]"
    return f"{name} + (long) k * {a.size}"


def _address(a, m: str | None = None) -> str:
    name = f"{a.name}_{m}" if m and a.name in OWN else a.name
    return f"{name} + (long) k * {a.size}"


def multi_loop(model: str, spec: FilterSpec, kernels: dict[str, Kernel]) -> str:
    """The C text of ``<model>_<filter>_run_multi`` (see the module docstring)."""
    predict = kernels[spec.predict]
    sizes = {a.name: a.size for a in predict.inputs}
    M = len(spec.update)
    fixed_terms = [f"symkf_finite({'&' if passing(a, None) == 'value' else ''}{a.name}, {a.size})"
                   for a in _shared(spec, kernels) if a.name != "u"]
    for m, name in spec.update.items():
        fixed_terms += [f"symkf_finite({'&' if passing(a, kernels[name]) == 'value' else ''}{a.name}_{m}, {a.size})"
                        for a in kernels[name].inputs if a.name in OWN and a.name not in OWN_PER_STEP and a.size]
    u_terms = [f"symkf_finite({_address(a)}, {a.size})" for a in predict.inputs if a.name == "u" and a.size]
    z_size = max([a.size for n in spec.update.values() for a in kernels[n].inputs if a.name == "z"] + [1])
    lines = [f"int {model}_{spec.name}_run_multi({', '.join(multi_params(spec, kernels))}) {{",
             f"  casadi_real x_first[{sizes['x']}], P_first[{sizes['P']}], z_used[{z_size}], t_next;",
             "  const casadi_real *x = x_first, *P = P_first;",
             "  int k, i, code, present, first_error = SYMKF_OK;",
             "  if (n_steps < 0) return SYMKF_ERR_ARGS;",
             f"  const int fixed_finite = {' && '.join(fixed_terms or ['1'])};",
             f"  for (i = 0; i < {sizes['x']}; ++i) x_first[i] = x0[i];",
             f"  for (i = 0; i < {sizes['P']}; ++i) P_first[i] = P0[i];",
             "  for (k = 0; k < n_steps; ++k) {",
             f"    casadi_real *x_at = x_hist + (long) k * {sizes['x']}, *P_at = P_hist + (long) k * {sizes['P']};",
             "    code = SYMKF_ERR_NONFINITE;",
             f"    if ({' && '.join(['fixed_finite', 'symkf_finite(&t[k], 1)', 'symkf_finite(&dt[k], 1)'] + u_terms)})"]
    args = {"t": "t[k]", "dt": "dt[k]", "x": "x", "P": "P"}
    call = [args.get(a.name, _value(a, predict)) for a in predict.inputs if passing(a, predict) != "omit"]
    lines += [f"      code = {model}_{predict.name}_eval({', '.join(call + ['x_at', 'P_at'])});",
              f"    status_hist[(long) k * {M + 1}] = code;",
              "    if (code != SYMKF_OK) {                 /* the state it was given; no update */",
              f"      for (i = 0; i < {sizes['x']}; ++i) x_at[i] = x[i];",
              f"      for (i = 0; i < {sizes['P']}; ++i) P_at[i] = P[i];",
              f"      for (i = 1; i <= {M}; ++i) status_hist[(long) k * {M + 1} + i] = code;",
              "      if (first_error == SYMKF_OK) first_error = code;",
              "      continue;", "    }",
              "    x = x_at;", "    P = P_at;", "    t_next = t[k] + dt[k];"]
    for j, (m, name) in enumerate(spec.update.items()):
        lines += _update_lines(model, m, kernels[name], spec, j, M)
    lines += ["  }", "  return first_error;", "}", ""]
    return "\n".join(lines)


def _update_lines(model: str, m: str, kernel: Kernel, spec: FilterSpec, j: int, M: int) -> list[str]:
    """Measurement ``m``'s update at step k, if present (in place on the step's row)."""
    inputs = {a.name: a for a in kernel.inputs}
    mask, z = inputs["mask"], inputs["z"]

    def mask_at(i) -> str:
        return f"mask_{m}[(long) k * {mask.size} + {i}]"
    lines = [f"    present = {' || '.join(f'{mask_at(i)} > (casadi_real) 0.5' for i in range(mask.size))};",
             "    code = SYMKF_OK;", "    if (present) {"]
    if sanitised_z(kernel):
        lines.append(f"      for (i = 0; i < {z.size}; ++i) z_used[i] = {mask_at('i')} > (casadi_real) 0.5 ? "
                     f"z_{m}[(long) k * {z.size} + i] : (casadi_real) 0;")
    else:
        lines.append(f"      for (i = 0; i < {z.size}; ++i) z_used[i] = z_{m}[(long) k * {z.size} + i];")
    per_step = [a for a in kernel.inputs if a.name in ("q", "mask") and a.size]
    terms = [f"symkf_finite({_address(a, m)}, {a.size})" for a in per_step] + [f"symkf_finite(z_used, {z.size})"]
    args = {"t": "t_next", "x": "x_at", "P": "P_at", "z": "z_used" if z.size > 1 else "z_used[0]"}
    call = [args.get(a.name, _value(a, kernel, m)) for a in kernel.inputs if passing(a, kernel) != "omit"]
    outputs = ["x_at", "P_at"] + [f"{a.name}_{m}_hist + (long) k * {a.size}" for a in kernel.outputs[:-1]
                                  if a.name in spec.diagnostics]
    lines += ["      code = SYMKF_ERR_NONFINITE;",
              f"      if ({' && '.join(terms)})",
              f"        code = {model}_{kernel.name}_eval({', '.join(call + outputs)});",
              "    }",
              f"    status_hist[(long) k * {M + 1} + {j + 1}] = code;",
              "    if (code != SYMKF_OK && code != SYMKF_GATED && first_error == SYMKF_OK) first_error = code;"]
    return lines


def multi_doc(model: str, spec: FilterSpec, kernels: dict[str, Kernel]) -> list[str]:
    """The header's description of ``_run_multi`` and its array sizes."""
    name = f"{model}_{spec.name}_run_multi"
    M = len(spec.update)
    per_step = []
    for m, kernel in spec.update.items():
        per_step += [f"{a.name}_{m} (n_steps * {a.size})" for a in kernels[kernel].inputs
                     if a.name in OWN_PER_STEP and a.size]
    return ["/**", f" * {name}: one time loop over a record of {M} measurements "
            f"({', '.join(spec.update)}), in that order at each step:",
            f" *   predict from t[k] over dt[k] ({model}_{spec.predict}), then update with each measurement present",
            " *   (a mask entry > 0.5) at t[k] + dt[k]. Per step: t, dt" + (", u" if any(
                a.name == "u" and a.size for a in kernels[spec.predict].inputs) else "") + ", "
            + ", ".join(per_step) + ";",
            " *   the other inputs are constant. Histories: x_hist, P_hist after step k; each measurement's y, S",
            f" *   (row k written when it updated); status_hist (n_steps * {M + 1} ints): step k's prediction code,",
            " *   then each update's (SYMKF_OK when absent). A failed prediction keeps the state and skips the",
            " *   step's updates; a failed update keeps the state it was given. No heap.",
            " * Returns: the first SYMKF_ERR_* code, SYMKF_ERR_ARGS if n_steps < 0, else SYMKF_OK.",
            f" * Stack: {name.upper()}_STACK_BYTES bytes (worst call path, measured by the compiler).", " */"]

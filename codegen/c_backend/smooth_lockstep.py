"""``<model>_<smoother>_run_lockstep``: the backward passes of several forward runs in lockstep.

The smoother's backward loop (c_backend/smooth_loop.py) for 4 runs per AVX2 vector: runs that
share t, dt, u and the constants (a campaign's), each with its own filtered histories. Backward
step k of each run is its lanes' result when the scalar loop would have taken it cleanly (row k
and the step's inputs finite, no branch condition set, status 0, outputs finite); a step over a
refused forward step carries the smoothed row (as the scalar loop), and any other step is the
scalar backward step itself (``<model>_<kernel>``, the checked C API function): each run's xs, Ps
and codes are ``<kernel>_run``'s bit for bit.
"""
from __future__ import annotations

from ..spec import STATUS_ARGS, STATUS_NONFINITE, STATUS_OK, Kernel
from .lockstep import LockstepSpec, scalar_call, scalar_prototype, vector_function
from .vector_c import WIDTH

FILTERED, SMOOTHED = ("x", "P"), ("xs", "Ps")


def smooth_lockstep_params(kernel: Kernel) -> list[str]:
    """``(n_runs, n_steps, <each input but xs, Ps>, status_hist, xs_hist, Ps_hist, smooth_status)``:
    x, P as each run's forward history (n_runs x n_steps blocks), per-step inputs (n_steps blocks)
    and constants shared, all by address."""
    params = ["int n_runs", "int n_steps"]
    for a in kernel.inputs:
        if a.name in SMOOTHED:
            continue
        params.append(f"const double *{a.name}_hist" if a.name in FILTERED else f"const double *{a.name}")
    return params + ["const int *status_hist", "double *xs_hist", "double *Ps_hist", "int *smooth_status"]


#: What the scalar backward step of lane l at row k reads for t, dt, the filtered and smoothed rows.
BACKWARD_INPUTS = {"t": "t[k + 1]", "dt": "dt[k + 1]", "x": "x_row", "P": "P_row", "xs": "xs_next", "Ps": "Ps_next"}


def smooth_lockstep_function(model: str, spec: LockstepSpec) -> str:
    kernel, W = spec.kernel, WIDTH
    name = f"{model}_{kernel.name}"
    params = smooth_lockstep_params(kernel)
    sizes = {a.name: a.size for a in kernel.inputs}
    n, nP = sizes["x"], sizes["P"]
    fixed = [a.name for a in kernel.inputs if a.name not in kernel.per_step and a.name not in SMOOTHED and a.size]
    ahead = [a.name for a in kernel.inputs if a.name in kernel.per_step and a.name not in FILTERED and a.size]
    fixed_finite = " && ".join([f"symkf_lockstep_finite({f}, {sizes[f]})" for f in fixed] or ["1"])
    ahead_finite = " && ".join(f"symkf_lockstep_finite({a} + (long) (k + 1) * {sizes[a]}, {sizes[a]})" for a in ahead)
    rows = "const long at = (long) run[l] * n_steps + k"
    return "\n".join([
        *vector_function(f"{name}_lanes", spec.flat, spec.vector_math), *vector_function(f"{name}_flags", spec.flags),
        scalar_prototype(model, kernel), "",
        f"__attribute__((target(\"avx2\"))) static int {name}_lockstep_avx2({', '.join(params)}) {{",
        *[f"  symkf_v4 in_{a.name}[{max(a.size, 1)}];" for a in kernel.inputs],
        f"  symkf_v4 out_xs[{n}], out_Ps[{nP}], out_status[1], flag[1];",
        f"  const symkf_v4 *in[{len(kernel.inputs)}];",
        "  symkf_v4 *out[3], *flag_out[1];",
        f"  long run[{W}];",
        f"  int first_error = {STATUS_OK}, k, l, i, g, code, lanes_ok[{W}], carried[{W}];",
        f"  const int fixed_finite = {fixed_finite};",
        *[f"  in[{i}] = in_{a.name};" for i, a in enumerate(kernel.inputs)],
        *[f"  (void){a.name};" for a in kernel.inputs if not a.size],
        "  out[0] = out_xs; out[1] = out_Ps; out[2] = out_status; flag_out[0] = flag;",
        *[f"  for (i = 0; i < {sizes[f]}; ++i) in_{f}[i] = SYMKF_SPLAT({f}[i]);" for f in fixed],
        "  if (n_steps == 0) return first_error;",
        f"  for (g = 0; g < n_runs; g += {W}) {{",
        f"    for (l = 0; l < {W}; ++l) run[l] = g + l < n_runs ? g + l : n_runs - 1;",
        f"    for (l = 0; l < {W} && g + l < n_runs; ++l) {{     /* the last row: smoothed = filtered */",
        "      const long at = (long) run[l] * n_steps + n_steps - 1;",
        f"      memcpy(xs_hist + at * {n}, x_hist + at * {n}, {n} * sizeof(double));",
        f"      memcpy(Ps_hist + at * {nP}, P_hist + at * {nP}, {nP} * sizeof(double));",
        f"      smooth_status[at] = fixed_finite ? {STATUS_OK} : {STATUS_NONFINITE};",
        f"      if (first_error == {STATUS_OK}) first_error = smooth_status[at];",
        "    }",
        "    for (k = n_steps - 2; k >= 0; --k) {",
        f"      const int step_finite = fixed_finite{' && ' + ahead_finite if ahead_finite else ''};",
        "      in_t[0] = SYMKF_SPLAT(t[k + 1]); in_dt[0] = SYMKF_SPLAT(dt[k + 1]);",
        *[f"      for (i = 0; i < {sizes[a]}; ++i) in_{a}[i] = SYMKF_SPLAT({a}[(long) (k + 1) * {sizes[a]} + i]);"
          for a in ahead if a not in ("t", "dt")],
        f"      for (l = 0; l < {W}; ++l) {{",
        f"        {rows};",
        f"        const int forward = status_hist[at + 1];",
        "        carried[l] = forward != SYMKF_LOCKSTEP_OK && forward != SYMKF_LOCKSTEP_GATED;",
        f"        lanes_ok[l] = !carried[l] && symkf_lockstep_finite(x_hist + at * {n}, {n}) && "
        f"symkf_lockstep_finite(P_hist + at * {nP}, {nP});",
        f"        for (i = 0; i < {n}; ++i) {{ in_x[i][l] = x_hist[at * {n} + i]; in_xs[i][l] = xs_hist[(at + 1) * {n} + i]; }}",
        f"        for (i = 0; i < {nP}; ++i) {{ in_P[i][l] = P_hist[at * {nP} + i]; "
        f"in_Ps[i][l] = Ps_hist[(at + 1) * {nP} + i]; }}",
        "      }",
        f"      if (step_finite) {{ {name}_flags(in, flag_out); if (lanes_wanted(flag[0], lanes_ok)) {name}_lanes(in, out); }}",
        f"      for (l = 0; l < {W} && g + l < n_runs; ++l) {{",
        f"        {rows};",
        f"        const double *x_row = x_hist + at * {n}, *P_row = P_hist + at * {nP};",
        f"        const double *xs_next = xs_hist + (at + 1) * {n}, *Ps_next = Ps_hist + (at + 1) * {nP};",
        f"        double *xs_row = xs_hist + at * {n}, *Ps_row = Ps_hist + at * {nP};",
        "        int clean = step_finite && lanes_ok[l] && flag[0][l] == 0. && out_status[0][l] == 0.;",
        f"        for (i = 0; i < {n} && clean; ++i) clean = symkf_lockstep_finite_value(out_xs[i][l]);",
        f"        for (i = 0; i < {nP} && clean; ++i) clean = symkf_lockstep_finite_value(out_Ps[i][l]);",
        "        if (carried[l]) {                /* the forward run kept row k as row k + 1 */",
        f"          memcpy(xs_row, xs_next, {n} * sizeof(double)); memcpy(Ps_row, Ps_next, {nP} * sizeof(double));",
        f"          code = {STATUS_OK};",
        "        } else if (clean) {",
        f"          for (i = 0; i < {n}; ++i) xs_row[i] = out_xs[i][l];",
        f"          for (i = 0; i < {nP}; ++i) Ps_row[i] = out_Ps[i][l];",
        f"          code = {STATUS_OK};",
        "        } else {",
        f"          code = {scalar_call(model, kernel, BACKWARD_INPUTS, 'k + 1', ['xs_row', 'Ps_row'])};",
        f"          if (code != {STATUS_OK}) {{       /* the filtered row k */",
        f"            memcpy(xs_row, x_row, {n} * sizeof(double)); memcpy(Ps_row, P_row, {nP} * sizeof(double));",
        f"            if (first_error == {STATUS_OK}) first_error = code;",
        "          }",
        "        }",
        "        smooth_status[at] = code;",
        "      }", "    }", "  }", "  return first_error;", "}", "",
        f"int {name}_run_lockstep({', '.join(params)}) {{",
        f"  if (n_runs < 0 || n_steps < 0 || !__builtin_cpu_supports(\"avx2\")) return {STATUS_ARGS};",
        f"  return {name}_lockstep_avx2({', '.join(p.split()[-1].lstrip('*') for p in params)});",
        "}", ""])

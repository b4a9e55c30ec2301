"""``<model>_<kernel>_run_lockstep``: Monte Carlo runs of one filter stepped in lockstep, 4 per vector.

A campaign runs one filter many times over the same clock: the same t, dt, u and station
parameters q, the same constants, each run its own measurements z (and mask). This loop steps
:data:`~symkf.codegen.c_backend.vector_c.WIDTH` runs at once: the whole step (the prediction, the
model's f_d and its Jacobian, h and its Jacobian, the update) is one straight-line algorithm
(c_backend/flatten.py) evaluated on vectors of one value per run (c_backend/vector_c.py), every
libm call the scalar one lane by lane (or, with ``<family>_lockstep_vector_math``, the
prediction's are libmvec's, one call for all lanes: each run's numbers then differ from the scalar
code's by its round-off). A lane's result is taken as it is only when the scalar step would have
succeeded on it: the inputs finite, no event in the step (the lanes evaluate the step's plain
branch), both kernels' status 0 and every output finite. Any other lane — a refused, gated,
masked-out or event step — is the scalar step itself (``<model>_<kernel>``, the checked C API
function), so the codes, histories and kept states are those of ``<kernel>_run_diag`` for each run,
bit for bit without vector math (tests/codegen/test_lockstep.py). The branch conditions always use
libm's scalar calls, so each lane takes the branch the scalar code takes.

Host library only, like the UKF's lanes: the unit compiles to nothing without ``SYMKF_LANES``
(the flight bundle's Makefile) and the loop returns SYMKF_ERR_ARGS on a CPU without AVX2
(``<model>_lockstep_available`` says which); the runtime then runs each run alone.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import casadi as ca

from ..discretize import event_in_step
from ..spec import STATUS_ARGS, STATUS_GATED, STATUS_OK, Kernel
from .api import param_list
from .arguments import passing, sanitised_z
from .flatten import Flattener, Substitute
from .vector_c import PRELUDE, WIDTH, libmvec_build, vector_body, vector_build


#: Per-step inputs that each run has its own of (the rest of a run's inputs are shared).
PER_RUN = ("z", "mask")
#: What the scalar step of lane l at step k reads for t, dt and the state.
STEP_INPUTS = {"t": "t[k]", "dt": "dt[k]", "x": "xs[l]", "P": "Ps[l]"}
#: Flags of the lockstep unit in the library (AVX2 without FMA: the scalar code's roundings).
UNIT_FLAGS = ["-DSYMKF_LANES", "-O2", "-ffp-contract=off"]


@dataclass(frozen=True)
class LockstepSpec:
    """A fused step kernel (``kernel``: its arguments) and its straight-line form, valid where
    ``flags`` (the step's inputs -> 1 where the C would take another branch: an event in the step,
    a nonzero centre weight) is 0. A filter step is two stages: ``flat`` (the step's inputs) ->
    (predicted x, P, predict status) and ``update_flat`` (the step's inputs, predicted x, P) ->
    (x, P, y, S, update status); a smoother's backward step is ``flat`` alone (inputs -> xs, Ps,
    status). ``vector_math``: ``flat``'s sin, cos, exp, log, pow, atan2 are libmvec's (the update's
    stay libm's: h forms positions at the Earth's radius, where a few ulp of a sine move a chaotic
    run's whole flight)."""

    kernel: Kernel
    flat: ca.Function
    flags: ca.Function
    update_flat: ca.Function | None = None
    vector_math: bool = False


def enabled(config, family: str) -> bool:
    """Lockstep loops of ``family`` for this configuration: ``<family>_lockstep`` (default off: the
    units add about 1.4 s (EKF) and 3.2 s (UKF) of compiler CPU per launcher measurement to every
    build and every edit of the model; the launcher campaign's builds turn them on), double
    precision, an x86-64 host."""
    return bool(config.get(f"{family}_lockstep", False)) and vector_build(config)


def uses_vector_math(config, family: str) -> bool:
    """``<family>_lockstep_vector_math`` on a host with glibc's libmvec: the prediction's lockstep
    lanes call it (default off, and without libmvec: the scalar code's numbers bit for bit)."""
    return bool(config.get(f"{family}_lockstep_vector_math", False)) and libmvec_build(config)


def host_flags(config, unit: str) -> list[str]:
    """The library's flags of a lockstep unit (none in the bundle's Makefile: an empty unit there)."""
    return list(UNIT_FLAGS) if unit.endswith("_lockstep.c") else []


def lockstep_file(model: str, kernel: str) -> str:
    return f"{model}_{kernel}_lockstep.c"


def spec_of(step: Kernel, predict: Kernel, update: Kernel, substitutes: dict) -> LockstepSpec | None:
    """The lockstep form of a fused step, or None if it has none here (a trusted partner or
    variants, or an operation the re-play or the vector C does not cover)."""
    if step.trusted or step.variants or len(step.parts) != 2 or step.carried != ("x", "P") or \
            not {"x", "P", "y", "S"} <= {a.name for a in step.outputs}:
        return None
    try:
        return LockstepSpec(step, *_straight_line(step, predict, update, substitutes))
    except NotImplementedError:
        return None


def substitutes_of(propagation) -> dict[str, Substitute]:
    """What stands in for a propagation's branching functions (c_backend/flatten.py): each event
    dispatcher's plain branch (another branch when an event lies in (t, t + dt]) and each weight
    switch's centre-free branch (the full one when the centre weight is not 0)."""
    events = propagation.branches.events

    def event_inside(operands):
        return event_in_step(operands[0][0], operands[1][0], events)
    out = {name: Substitute(fn, event_inside) for name, fn in propagation.branches.plain_functions.items()}
    out.update({name: Substitute(free, lambda operands: operands[0][0] != 0, drops_first=True)
                for name, free in propagation.weight_switches.items()})
    return out


def _straight_line(step: Kernel, predict: Kernel, update: Kernel, substitutes: dict):
    """(the prediction as one SX Function of the step's inputs -> predicted x, P, status; the
    branch conditions as one of the same inputs -> flag; the update as one of the step's inputs
    and the predicted x, P -> x, P, y, S, status)."""
    symbols = {a.name: ca.SX.sym(a.name, *a.shape) for a in step.inputs}
    flattener = Flattener(substitutes)

    def nonzeros(matrix):
        return [matrix.nz[i] for i in range(matrix.nnz())]

    def run(kernel: Kernel, given: dict):
        fn = kernel.function
        values = [given[fn.name_in(i)] for i in range(fn.n_in())]
        if any(not fn.sparsity_in(i).is_dense() or v.nnz() != fn.nnz_in(i) for i, v in enumerate(values)):
            raise NotImplementedError(f"lockstep: {fn.name()} has a sparse input")
        outs = flattener.flat(fn, [nonzeros(v) for v in values])
        return {fn.name_out(i): ca.vertcat(*outs[i]) if outs[i] else ca.SX(0, 1) for i in range(fn.n_out())}
    predicted = run(predict, symbols)
    x_mid, P_mid = ca.SX.sym("x_predicted", *symbols["x"].shape), ca.SX.sym("P_predicted", *symbols["P"].shape)
    t_next = symbols["t"] + symbols["dt"]                  # as the C step: t_next = t + dt
    updated = run(update, {**symbols, "t": t_next, "x": x_mid, "P": P_mid})
    inputs = [symbols[a.name] for a in step.inputs]
    prediction = ca.Function(f"{step.name}_lockstep_predict", inputs,
                             [predicted["x"], predicted["P"], predicted["status"]], {"cse": True})
    update_fn = ca.Function(f"{step.name}_lockstep_update", inputs + [x_mid, P_mid],
                            [updated[n] for n in ("x", "P", "y", "S", "status")], {"cse": True})
    flags = _flags_function(f"{step.name}_lockstep_flags", inputs, flattener.conditions)
    sizes = {a.name: a.size for a in step.outputs}
    if [update_fn.nnz_out(i) for i in range(5)] != [sizes[n] for n in ("x", "P", "y", "S", "status")] or \
            [prediction.nnz_out(i) for i in range(2)] != [sizes["x"], sizes["P"]]:
        raise NotImplementedError("lockstep: a sparse output")
    vector_body(prediction), vector_body(update_fn), vector_body(flags)      # NotImplementedError: no lockstep
    return prediction, flags, update_fn


def _flags_function(name: str, inputs: list, conditions: list) -> ca.Function:
    """1 where any of the branch ``conditions`` holds (the lanes' result is not the C's there);
    a condition that is not a function of ``inputs`` alone (one on the predicted state): no lockstep."""
    flag = ca.SX(0)
    for condition in conditions:
        flag = ca.logic_or(flag, condition)
    try:
        return ca.Function(name, inputs, [flag], {"cse": True})
    except RuntimeError as exc:                              # free variables: a condition on the predicted state
        raise NotImplementedError(f"lockstep: {exc}") from None


def smoother_spec_of(kernel: Kernel, substitutes: dict) -> LockstepSpec | None:
    """The lockstep form of a smoother's backward step (inputs -> xs, Ps, status), or None."""
    if kernel.backward != ("xs", "Ps") or kernel.trusted or kernel.variants:
        return None
    try:
        symbols = [ca.SX.sym(a.name, *a.shape) for a in kernel.inputs]
        fn = kernel.function
        if any(not fn.sparsity_in(i).is_dense() for i in range(fn.n_in())):
            raise NotImplementedError("lockstep: a sparse input")
        flattener = Flattener(substitutes)
        outs = flattener.flat(fn, [[s.nz[i] for i in range(s.nnz())] for s in symbols])
        flat = ca.Function(f"{kernel.name}_lockstep", symbols, [ca.vertcat(*o) for o in outs], {"cse": True})
        flags = _flags_function(f"{kernel.name}_lockstep_flags", symbols, flattener.conditions)
        vector_body(flat), vector_body(flags)
        return LockstepSpec(kernel, flat, flags)
    except NotImplementedError:
        return None


def specs_of(bundle_kernels, filters, propagation, vector_math: bool = False) -> tuple[LockstepSpec, ...]:
    """The lockstep forms of a family's fused steps (``filters``: its FilterSpecs; ``propagation``:
    its f_d's :class:`~symkf.codegen.model_functions.Propagation`; ``vector_math``: libmvec's calls)."""
    kernels = {k.name: k for k in bundle_kernels}
    substitutes = substitutes_of(propagation)
    made = []
    for spec in filters:
        for step in spec.step.values():
            step_kernel = kernels[step]
            if len(step_kernel.parts) == 2:
                made.append(spec_of(step_kernel, kernels[step_kernel.parts[0]], kernels[step_kernel.parts[1]],
                                    substitutes))
        if spec.smooth:
            made.append(smoother_spec_of(kernels[spec.smooth], substitutes))
    return tuple(replace(m, vector_math=vector_math) for m in made if m is not None)


# ---------------------------------------------------------------------- C
def _sizes(spec: LockstepSpec) -> dict[str, int]:
    return {a.name: a.size for a in spec.kernel.inputs}


def lockstep_params(spec: LockstepSpec) -> list[str]:
    """``(n_runs, n_steps, <each input of the step>, x_hist, P_hist, y_hist, S_hist, status_hist)``:
    every input by address (per step: n_steps blocks; per run: n_runs x n_steps blocks; x, P: the
    initial state, shared), the histories n_runs x n_steps blocks."""
    params = ["int n_runs", "int n_steps"]
    for a in spec.kernel.inputs:
        params.append(f"const double *{a.name}0" if a.name in ("x", "P") else f"const double *{a.name}")
    params += [f"double *{name}_hist" for name in ("x", "P", "y", "S")]
    return params + ["int *status_hist"]


def scalar_call(model: str, kernel: Kernel, where: dict[str, str], step: str, outputs: list[str],
                per_run: str | None = None) -> str:
    """A call of the checked scalar step ``<model>_<kernel>``: the inputs in ``where`` as given,
    per-run inputs at row ``per_run`` of theirs, per-step inputs at ``step``, constants as they are
    (a scalar one by value); ``outputs``: where it writes."""
    args = []
    for a in kernel.inputs:
        how = passing(a, kernel)
        if how == "omit":
            continue
        if a.name in where:
            args.append(where[a.name])
            continue
        if per_run and a.name in PER_RUN:
            expr = f"{a.name} + ({per_run}) * {a.size}"
        elif a.name in kernel.per_step:
            expr = f"{a.name} + (long) ({step}) * {a.size}"
        else:
            expr = a.name
        args.append(f"*({expr})" if how == "value" else expr)
    return f"{model}_{kernel.name}({', '.join(args + outputs)})"


def scalar_prototype(model: str, kernel: Kernel) -> str:
    return f"int {model}_{kernel.name}({', '.join(param_list(kernel))});   /* {model}_api.c: the checked scalar step */"


def vector_function(name: str, fn: ca.Function, vector_math: bool = False) -> list[str]:
    return [f"__attribute__((target(\"avx2\"))) static void {name}(const symkf_v4 *const *in, symkf_v4 *const *out) {{",
            "  (void)in;                 /* (a constant function reads no input) */",
            *(f"  {line}" for line in vector_body(fn, vector_math)), "}", ""]


def lockstep_function(model: str, spec: LockstepSpec) -> str:
    """The C of one filter step's lockstep loop (see the module docstring)."""
    kernel, W = spec.kernel, WIDTH
    name = f"{model}_{kernel.name}"
    params = lockstep_params(spec)
    return "\n".join([
        *vector_function(f"{name}_lanes_predict", spec.flat, spec.vector_math),
        *vector_function(f"{name}_lanes_update", spec.update_flat), *_two_stages(name, kernel),
        *vector_function(f"{name}_flags", spec.flags),
        scalar_prototype(model, kernel), "",
        f"__attribute__((target(\"avx2\"))) static int {name}_lockstep_avx2({', '.join(params)}) {{",
        *_declarations(kernel),
        f"  for (g = 0; g < n_runs; g += {W}) {{",
        *_group_start(kernel),
        "    for (k = 0; k < n_steps; ++k) {",
        *_gather(kernel),
        f"      if (step_finite) {{ {name}_flags(in, flag_out); if (lanes_wanted(flag[0], lanes_ok)) {name}_lanes(in, out); }}",
        f"      for (l = 0; l < {W} && g + l < n_runs; ++l) {{",
        *_lane_result(model, kernel),
        "      }", "    }", "  }", "  return first_error;", "}", "",
        f"int {name}_run_lockstep({', '.join(params)}) {{",
        f"  if (n_runs < 0 || n_steps < 0 || !__builtin_cpu_supports(\"avx2\")) return {STATUS_ARGS};",
        f"  return {name}_lockstep_avx2({', '.join(p.split()[-1].lstrip('*') for p in params)});",
        "}", ""])


def _two_stages(name: str, kernel: Kernel) -> list[str]:
    """``<name>_lanes``: the prediction's lanes, then the update's on the predicted x, P (out[5]:
    the prediction's status)."""
    sizes, n_in = {a.name: a.size for a in kernel.inputs}, len(kernel.inputs)
    return [f"__attribute__((target(\"avx2\"))) static void {name}_lanes(const symkf_v4 *const *in, "
            "symkf_v4 *const *out) {",
            f"  symkf_v4 x_predicted[{sizes['x']}], P_predicted[{sizes['P']}];",
            f"  symkf_v4 *const predicted[3] = {{x_predicted, P_predicted, out[5]}};",
            f"  const symkf_v4 *update_in[{n_in + 2}];",
            "  int i;",
            f"  for (i = 0; i < {n_in}; ++i) update_in[i] = in[i];",
            f"  update_in[{n_in}] = x_predicted; update_in[{n_in + 1}] = P_predicted;",
            f"  {name}_lanes_predict(in, predicted);",
            f"  {name}_lanes_update(update_in, out);",
            "}", ""]


def _declarations(kernel: Kernel) -> list[str]:
    """The loop's locals: each input and output as vectors, the lanes' states and runs, the fixed
    inputs' finiteness (tested once) and their vectors."""
    W, sizes, outs = WIDTH, {a.name: a.size for a in kernel.inputs}, {a.name: a.size for a in kernel.outputs}
    fixed = [a.name for a in kernel.inputs if a.name not in kernel.per_step and a.name not in ("x", "P") and a.size]
    finite = [f"symkf_lockstep_finite({n}, {sizes[n]})" for n in fixed]
    finite += [f"symkf_lockstep_finite({n}0, {sizes[n]})" for n in ("x", "P")]
    return [*[f"  symkf_v4 in_{a.name}[{max(a.size, 1)}];" for a in kernel.inputs],
            *[f"  symkf_v4 out_{n}[{max(outs[n], 1)}];" for n in ("x", "P", "y", "S")],
            "  symkf_v4 out_status[1], out_predicted[1], flag[1];",
            f"  const symkf_v4 *in[{len(kernel.inputs)}];",
            "  symkf_v4 *out[6], *flag_out[1];",
            f"  double x_first[{W}][{sizes['x']}], P_first[{W}][{sizes['P']}];",
            f"  const double *xs[{W}], *Ps[{W}];",
            f"  long run[{W}];",
            f"  int first_error = {STATUS_OK}, k, l, i, g, lanes_ok[{W}];",
            f"  const int fixed_finite = {' && '.join(finite)};",
            *[f"  in[{i}] = in_{a.name};" for i, a in enumerate(kernel.inputs)],
            *[f"  (void){a.name};" for a in kernel.inputs if not a.size],
            "  out[0] = out_x; out[1] = out_P; out[2] = out_y; out[3] = out_S;",
            "  out[4] = out_status; out[5] = out_predicted; flag_out[0] = flag;",
            *[f"  for (i = 0; i < {sizes[n]}; ++i) in_{n}[i] = SYMKF_SPLAT({n}[i]);" for n in fixed]]


def _group_start(kernel: Kernel) -> list[str]:
    W, sizes = WIDTH, {a.name: a.size for a in kernel.inputs}
    return [f"    for (l = 0; l < {W}; ++l) {{            /* lanes past the last run repeat it (not written) */",
            "      run[l] = g + l < n_runs ? g + l : n_runs - 1;",
            f"      for (i = 0; i < {sizes['x']}; ++i) x_first[l][i] = x0[i];",
            f"      for (i = 0; i < {sizes['P']}; ++i) P_first[l][i] = P0[i];",
            "      xs[l] = x_first[l]; Ps[l] = P_first[l];",
            "    }"]


def _gather(kernel: Kernel) -> list[str]:
    """Step k's inputs as vectors: the shared ones splat, each lane's state, z and mask in its lane."""
    W, sizes = WIDTH, {a.name: a.size for a in kernel.inputs}
    shared = [a.name for a in kernel.inputs if a.name in kernel.per_step and a.name not in PER_RUN + ("t", "dt")
              and a.size]
    finite = "".join(f" && symkf_lockstep_finite({n} + (long) k * {sizes[n]}, {sizes[n]})" for n in shared)
    return [f"      const int step_finite = fixed_finite && symkf_lockstep_finite(&t[k], 1) && "
            f"symkf_lockstep_finite(&dt[k], 1){finite};",
            "      in_t[0] = SYMKF_SPLAT(t[k]); in_dt[0] = SYMKF_SPLAT(dt[k]);",
            *[f"      for (i = 0; i < {sizes[n]}; ++i) in_{n}[i] = SYMKF_SPLAT({n}[(long) k * {sizes[n]} + i]);"
              for n in shared],
            f"      for (l = 0; l < {W}; ++l) {{",
            f"        for (i = 0; i < {sizes['x']}; ++i) in_x[i][l] = xs[l][i];",
            f"        for (i = 0; i < {sizes['P']}; ++i) in_P[i][l] = Ps[l][i];",
            *_per_run_lines(kernel, sanitised_z(kernel)),
            "      }"]


def _lane_result(model: str, kernel: Kernel) -> list[str]:
    """Lane l's step k: its lanes' result when clean, else the scalar step; then the state kept or advanced."""
    sizes, outs = {a.name: a.size for a in kernel.inputs}, {a.name: a.size for a in kernel.outputs}
    outputs = [f"{a.name}_row" for a in kernel.outputs[:-1] if a.size]
    return ["        const long row = (long) run[l] * n_steps + k;",
            *[f"        double *{n}_row = {n}_hist + row * {outs[n]};" for n in ("x", "P", "y", "S")],
            "        int code;",
            "        lanes_ok[l] = step_finite && lanes_ok[l] && flag[0][l] == 0. && out_predicted[0][l] == 0. && "
            "out_status[0][l] == 0.;",
            *[f"        for (i = 0; i < {outs[n]} && lanes_ok[l]; ++i) lanes_ok[l] = "
              f"symkf_lockstep_finite_value(out_{n}[i][l]);" for n in ("x", "P", "y", "S")],
            "        if (lanes_ok[l]) {",
            *[f"          for (i = 0; i < {outs[n]}; ++i) {n}_row[i] = out_{n}[i][l];" for n in ("x", "P", "y", "S")],
            f"          code = {STATUS_OK};",
            "        } else {",
            f"          code = {scalar_call(model, kernel, STEP_INPUTS, 'k', outputs, '(long) run[l] * n_steps + k')};",
            "        }",
            "        status_hist[row] = code;",
            "        if (code == SYMKF_LOCKSTEP_OK || code == SYMKF_LOCKSTEP_GATED) {",
            "          xs[l] = x_row; Ps[l] = P_row;",
            "        } else {                   /* the state it was given */",
            f"          for (i = 0; i < {sizes['x']}; ++i) x_row[i] = xs[l][i];",
            f"          for (i = 0; i < {sizes['P']}; ++i) P_row[i] = Ps[l][i];",
            "          if (first_error == SYMKF_LOCKSTEP_OK) first_error = code;",
            "        }"]


def _per_run_lines(kernel: Kernel, sanitised: bool) -> list[str]:
    """Lane l's z (masked components 0, as the scalar run's z_used) and mask, and whether they are finite."""
    sizes = {a.name: a.size for a in kernel.inputs}
    lines = ["        lanes_ok[l] = 1;"]
    for n in PER_RUN:
        if n in sizes and sizes[n]:
            lines.append(f"        const double *{n}_at = {n} + ((long) run[l] * n_steps + k) * {sizes[n]};")
    # a value that is not finite makes its lane the scalar step's, and enters the lanes as 0
    # (no NaN or Inf in the vector arithmetic: no floating-point exception there)
    if "mask" in sizes and sizes["mask"]:
        lines.append(f"        for (i = 0; i < {sizes['mask']}; ++i) {{ const int ok = symkf_lockstep_finite_value("
                     "mask_at[i]); in_mask[i][l] = ok ? mask_at[i] : 0.; lanes_ok[l] &= ok; }")
    if "z" in sizes and sizes["z"]:
        value = "mask_at[i] > 0.5 ? z_at[i] : 0." if sanitised else "z_at[i]"
        lines.append(f"        for (i = 0; i < {sizes['z']}; ++i) {{ const double v = {value}; "
                     "const int ok = symkf_lockstep_finite_value(v); in_z[i][l] = ok ? v : 0.; lanes_ok[l] &= ok; }")
    return lines

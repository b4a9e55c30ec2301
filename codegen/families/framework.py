"""The family framework every filter family builds on (one family per module in this folder).

- :func:`make_kernel` (the one way to declare a kernel) and :func:`compose_step` (predict then
  update as one kernel); :func:`model_kernels` for the stand-alone model functions.
- Shared update algebra: masked noise, wrapped masked innovation, gating, statuses, finiteness.
- :func:`filter_spec`: a family's filter from its kernels' names.
- :data:`FAMILIES` / :func:`register_family`: a model asks for families by name; a family
  registers with its typed options (frozen dataclasses, ``codegen.spec.declare_options``).

The model's own functions and the kernel arguments (:class:`~symkf.codegen.model_functions.Symbols`,
:class:`~symkf.codegen.model_functions.ModelFunctions`) are in ``codegen/model_functions.py``.
This module registers no family.

Every update takes an availability ``mask`` (1 = use, 0 = ignore): a masked component's
innovation is zero, its row of H and its sigma-point deviations are zero and its noise variance
is replaced by 1, so it contributes exactly nothing; an all-masked update returns x and P unchanged.
A failed factorisation returns a status code and the inputs x, P unchanged.
"""
from __future__ import annotations

from typing import Callable

import casadi as ca

from symkf.models.base import Model
from .. import linalg
from ..discretize import FUNCTION_OPTIONS, continuous_dynamics
from ..model_functions import Discretisation, ModelFunctions, Symbols
from ..spec import STATUS_GATED, STATUS_NONFINITE, STATUS_NOT_PD, Arg, Family, FilterSpec, Kernel, declare_options


def make_kernel(name: str, doc: str, symbols: Symbols, extra_sym: dict, extra_arg: dict,
            inputs: list[str], outputs: list[tuple[str, ca.SX]], carried=(), per_step=()) -> Kernel:
    sym = {**symbols.sym, **extra_sym}
    args = {**symbols.arg, **extra_arg}
    out_names = [o for o, _ in outputs]
    function = ca.Function(f"{symbols.model.name}_k_{name}", [sym[i] for i in inputs],
                           [ca.densify(expr) for _, expr in outputs], inputs, out_names, FUNCTION_OPTIONS)
    return Kernel(name, function, doc, tuple(args[i] for i in inputs),
                  tuple(args[o] if o in args else Arg(o, tuple(e.shape)) for o, e in outputs),
                  tuple(carried), tuple(per_step))


# ---------------------------------------------------------------------- model functions
def model_kernels(model: Model, symbols: Symbols, fns: ModelFunctions) -> list[Kernel]:
    """f, f_d, F = df_d/dx, and h, H = dh/dx for every measurement (those in
    ``model.generic_kernels``: a model whose filters need none of them can leave them out)."""
    s = symbols.sym
    f = continuous_dynamics(model)
    step_args = (s["t"], s["dt"], s["x"], s["u"], s["p"])
    kernels = [
        make_kernel("f", "Continuous dynamics dx/dt = f(t, x, u, p).", symbols, {}, {},
                ["t", "x", "u", "p"], [("xdot", f(s["t"], s["x"], s["u"], s["p"], fns.zero_w)), ("status", ca.SX(0))]),
        make_kernel("fd", "Discrete dynamics: RK4 from t to t + dt.", symbols, {}, {},
                ["t", "dt", "x", "u", "p"], [("x", fns.fd(*step_args)), ("status", ca.SX(0))]),
        make_kernel("jac_fd", "State-transition Jacobian F = d f_d / d x (derived by CasADi).", symbols, {}, {},
                ["t", "dt", "x", "u", "p"], [("F", fns.jac_fd(*step_args)), ("status", ca.SX(0))]),
    ]
    for name in model.measurements:
        msym, marg = symbols.measurement(name)
        meas_args = (s["t"], s["x"], s["u"], s["p"], msym["q"])
        kernels += [
            make_kernel(f"h_{name}", f"Measurement '{name}': z = h(t, x, u, p, q).", symbols, msym, marg,
                    ["t", "x", "u", "p", "q"], [("z", fns.h[name](*meas_args)), ("status", ca.SX(0))]),
            make_kernel(f"jac_h_{name}", f"Measurement Jacobian H = dh/dx of '{name}' (derived by CasADi).",
                    symbols, msym, marg, ["t", "x", "u", "p", "q"],
                    [("H", fns.jac_h[name](*meas_args)), ("status", ca.SX(0))]),
        ]
    wanted = _generic_names(model)
    return [k for k in kernels if k.name in wanted]


def _generic_names(model: Model) -> set[str]:
    wanted = set(model.generic_kernels)
    names = {"f", "fd", "jac_fd"} & wanted
    for name in model.measurements:
        names |= {f"h_{name}"} if "h" in wanted else set()
        names |= {f"jac_h_{name}"} if "jac_h" in wanted else set()
    return names


# ---------------------------------------------------------------------- shared update algebra
def masked_noise(R: ca.SX, mask: ca.SX) -> ca.SX:
    """R with masked rows/columns replaced by the identity's (keeps S positive definite)."""
    m = R.shape[0]
    return ca.vertcat(*[ca.horzcat(*[
        R[i, j] * mask[i] * mask[j] + (1 - mask[i]) * (1.0 if i == j else 0.0) for j in range(m)])
        for i in range(m)])


def innovation(z: ca.SX, z_pred: ca.SX, mask: ca.SX, wrap: tuple[bool, ...]) -> ca.SX:
    """z - z_pred, angles wrapped; masked components are exactly 0 even if z is NaN there."""
    rows = []
    for i, is_angle in enumerate(wrap):
        d = linalg.select(mask[i] > 0.5, z[i], z_pred[i]) - z_pred[i]      # a masked NaN enters no arithmetic
        rows.append(linalg.select(mask[i] > 0.5, linalg.wrap_angle(d) if is_angle else d, 0))
    return ca.vertcat(*rows)


def gated(gate: ca.SX, mask: ca.SX, nis: ca.SX) -> ca.SX:
    """1 if the normalised innovation squared ``nis`` = y^T S^-1 y exceeds the gate for the number
    k of used components (``gate[k-1]``; a gate <= 0 is off), else 0."""
    used = ca.sum1(mask)
    threshold = sum((ca.if_else(used == i + 1, gate[i], 0) for i in range(gate.shape[0])), 0)
    return (threshold > 0) * (nis > threshold)


def all_finite(values: list[ca.SX]) -> ca.SX:
    """1 if every entry of every value is finite, else 0: |sum of the entries x 2^-1000| < Inf (a NaN
    or an infinite entry makes the sum NaN or infinite; scaled finite entries cannot overflow it)."""
    total = ca.SX(0)
    for value in values:
        for i in range(value.numel()):
            total = total + value[i] * FINITE_SCALE
    return ca.fabs(total) < ca.inf


#: 2^-1000: scaled, any finite input has |v| < 2^24, so a sum of fewer than 2^999 of them is
#: finite; a NaN or an infinity makes the sum NaN or infinite. One multiply-add per entry.
FINITE_SCALE = 2.0 ** -1000


#: Argument order of every generated filter function (a kernel uses the subset it needs).
CANONICAL_ORDER = ("t", "dt", "x", "P", "u", "p", "Q", "q", "z", "mask", "R", "gate", "kappa")


def compose_step(name: str, predict: Kernel, update: Kernel) -> Kernel:
    """predict(t, dt) then update at t + dt, as one kernel that calls the two (no code copied).

    Inputs are the union of both kernels' inputs (predict's order first); outputs are the
    update's. If either part fails, x and P come back unchanged with the first failure's code.
    """
    inputs = list(predict.inputs) + [a for a in update.inputs if a.name not in {b.name for b in predict.inputs}]
    inputs.sort(key=lambda a: CANONICAL_ORDER.index(a.name) if a.name in CANONICAL_ORDER else len(CANONICAL_ORDER))
    sym = {a.name: ca.MX.sym(a.name, *a.shape) for a in inputs}
    pred = predict.function.call({a.name: sym[a.name] for a in predict.inputs})
    upd_args = {a.name: sym[a.name] for a in update.inputs}
    upd_args.update(t=sym["t"] + sym["dt"], x=pred["x"], P=pred["P"])
    upd = update.function.call(upd_args)
    failed_early = pred["status"] != 0
    outputs = []
    for a in update.outputs:
        value = upd[a.name]
        if a.name in ("x", "P"):
            value = ca.if_else(failed_early, sym[a.name], value)
        elif a.name == "status":
            value = ca.if_else(failed_early, pred["status"], value)
        outputs.append(value)
    model = predict.function.name().split("_k_")[0]
    function = ca.Function(f"{model}_k_{name}", [sym[a.name] for a in inputs], outputs,
                           [a.name for a in inputs], [a.name for a in update.outputs],
                           {"allow_duplicate_io_names": True})
    doc = f"{predict.doc.split(' (')[0]}; then {update.doc.replace(' at time t ', ' at t + dt ')} Both in one call."
    return Kernel(name, function, doc, tuple(inputs), update.outputs, carried=("x", "P"),
                  per_step=tuple(a.name for a in inputs if a.name in ("t", "dt", "u", "q", "z", "mask")),
                  parts=(predict.name, update.name))


def update_status(ok: ca.SX, is_gated: ca.SX, inputs_finite: ca.SX) -> ca.SX:
    """NONFINITE if an input is NaN/Inf, else NOT_PD if a factorisation failed, else GATED or 0."""
    status = linalg.select(is_gated, STATUS_GATED, 0)
    status = linalg.select(ok, status, STATUS_NOT_PD)
    return linalg.select(inputs_finite, status, STATUS_NONFINITE)


def update_outputs(update, x_old, P_old, gate, mask, inputs_finite, factor: bool = False):
    """x, P (unchanged unless the update succeeded and passed the gate), y, S, status. A covariance
    (``factor`` False: P itself, not a square-root factor) that the update writes must come out
    positive semi-definite (``linalg.psd_flag``), else NOT_PD: after a prediction that exploded
    (P ~ 1e247 from a step hours long) the update's round-off can leave finite negative variances."""
    x_new, P_new, y, S, ok, nis = update
    is_gated = gated(gate, mask, nis)
    if not factor:                                       # the covariance an update that is taken writes
        ok = ok * (is_gated + (1 - is_gated) * linalg.psd_flag(P_new))
    keep = ok * (1 - is_gated) * inputs_finite
    x_out, P_out = (linalg.select(keep, new, old) for new, old in ((x_new, x_old), (P_new, P_old)))
    return [("x", x_out), ("P", P_out), ("y", y), ("S", S), ("status", update_status(ok, is_gated, inputs_finite))]


def masked_finite(z: ca.SX, mask: ca.SX) -> ca.SX:
    """1 if every used component of z is finite (masked components may be NaN)."""
    flag = ca.SX(1)
    for i in range(z.shape[0]):
        flag = flag * ((mask[i] < 0.5) + (mask[i] >= 0.5) * linalg.finite_flag(z[i]))
    return flag


def filter_spec(name: str, algorithm: str, kernels: list[Kernel], measurements, **fields) -> FilterSpec:
    """The spec of filter ``name`` whose kernels follow the naming rule ``<name>_predict``,
    ``<name>_update_<measurement>``, ``<name>_step_<measurement>`` (those present in ``kernels``)."""
    names = {k.name for k in kernels}
    predict = f"{name}_predict" if f"{name}_predict" in names else ""
    update = {m: f"{name}_update_{m}" for m in measurements if f"{name}_update_{m}" in names}
    step = {m: f"{name}_step_{m}" for m in measurements if f"{name}_step_{m}" in names}
    if not step:
        raise ValueError(f"filter '{name}': no kernel named {name}_step_<measurement> among {sorted(names)}")
    return FilterSpec(name, algorithm, predict, update, step, **fields)


FamilyBuilder = Callable[[Model, Symbols, ModelFunctions], "Family"]

#: Filter families a model can ask for by name in ``Model.filters``. Each lives in
#: ``codegen/families/<algorithm>.py`` and calls :func:`register_family` when imported;
#: ``symkf.codegen.families`` imports them all.
FAMILIES: dict[str, FamilyBuilder] = {}
#: Families whose kernels call the bundle's longest compile (the UKF: f_d at 2n + 1 sigma points,
#: one function); a build generates them before the other families, so that unit compiles first.
LONG_COMPILE: set[str] = set()


#: Families that keep a quaternion state on the unit sphere (a chart, or a normalised estimate);
#: any other family treats a declared quaternion as four free states (:func:`check_quaternions`).
QUATERNION_FAMILIES: set[str] = set()


def register_family(name: str, builder: FamilyBuilder, long_compile: bool = False, options=(),
                    quaternions: bool = False) -> FamilyBuilder:
    """Make a filter family available to models by name (``long_compile``: see :data:`LONG_COMPILE`;
    ``quaternions``: it handles quaternion states, :data:`QUATERNION_FAMILIES`), with its
    discretisation options ``<name>_*`` (:class:`Discretisation`) and its own ``options``:
    frozen dataclasses whose fields are the options it reads, each named ``<prefix><field>`` with
    the class's ``prefix``."""
    if name in FAMILIES and FAMILIES[name] is not builder:
        raise ValueError(f"filter family '{name}' is registered twice")
    FAMILIES[name] = builder
    if long_compile:
        LONG_COMPILE.add(name)
    if quaternions:
        QUATERNION_FAMILIES.add(name)
    declare_options(Discretisation, f"family '{name}'", prefix=f"{name}_")
    for declared in options:
        declare_options(declared, f"family '{name}'", prefix=declared.prefix)
    return builder


def check_quaternions(model: Model) -> None:
    """A family without a quaternion chart asked for on a model with quaternion states is an error
    (it would treat each quaternion as four free states) unless the model says so on purpose in
    ``Model.quaternion_as_vector_families``."""
    if not model.quaternions:
        return
    unsure = [f for f in model.filters if f not in QUATERNION_FAMILIES and f not in model.quaternion_as_vector_families]
    if unsure:
        names = ", ".join(qs.name for qs in model.quaternions)
        charted = sorted(QUATERNION_FAMILIES - {"gradient_descent"})
        raise ValueError(f"model '{model.name}': filter famil{'ies' if len(unsure) > 1 else 'y'} {unsure} would treat "
                         f"quaternion state {names} as 4 free states (P {model.nx} x {model.nx}, |q| drifting from 1); "
                         f"ask for {charted} (error state on the rotation manifold), or set "
                         f"model.quaternion_as_vector_families = {tuple(unsure)!r} to generate them anyway")

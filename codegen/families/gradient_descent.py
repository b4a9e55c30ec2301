"""Gradient-descent orientation filter of paper 001 (Ryang, Kim 2020) as kernels: full form and
simplified form, built from the equations of the Model it is given (``models/marg.py``).

One step, from the previous estimate q (scalar-last, unit) and the samples of one time instant:

- gyro: q̇_ω = f(q, ω), the model's dynamics with the gyro as its input u ((7)-(8) for
  ``models/marg.py``), q_ω = q + q̇_ω Δt (9);
- correction direction: ∇f/‖∇f‖ with ∇f = Jᵀ f (13), (27), f = h(q) - z the model's measurement
  against the normalised sample, J = ∂f/∂q derived by CasADi: f = f_g (18) with measurement
  ``"imu"``, f = f_{g,b} (24) with ``"marg"``, whose parameters (the earth-field reference b) come
  from the model's ``earth_field_reference`` function at the previous estimate. A missing sample
  (mask 0 on any of its components) or a zero-norm one drops its rows of f; with none left (or
  ∇f = 0) the step is pure gyro integration: no NaN, q stays unit.
- full form (26)-(30): μ_t = α‖q̇_ω‖Δt, q_∇ = q - μ_t ∇f/‖∇f‖, γ_t = β / (μ_t/Δt + β),
  q_est = γ_t q_∇ + (1 - γ_t) q_ω; μ_t/Δt is evaluated as α‖q̇_ω‖ (no division by Δt);
- simplified form (31): q_est = q + (q̇_ω - β ∇f/‖∇f‖) Δt;
- both: q_est is normalised (the paper requires unit quaternions; (29) and (31) do not preserve it).

What the family needs of a model (checked, one-line error otherwise): four states (the quaternion,
scalar-last), three inputs (the gyro), parameters ``beta`` and ``alpha``, dynamics and
measurements that do not depend on t, measurements ``"imu"`` (3: accelerometer direction) and/or
``"marg"`` (6: accelerometer then magnetometer direction), and in ``Model.functions`` (a dict of
CasADi Functions) the documented names below: :data:`EARTH_FIELD_REFERENCE` (for ``"marg"``) and
:data:`INITIAL_ORIENTATION`.

Kernels (canonical arguments: dt, x = q, u = gyro, p = [beta, alpha], z the samples, mask which
components are present): ``gd_simple_<m>`` and ``gd_full_<m>`` per measurement m (carried x,
per-step dt, u, z, mask: the generic C run loop filters a whole recording with the real Δt of
every sample), and ``gd_initial_<m>`` (z -> x, orientation from the first sample). Filters
``gd_simple`` and ``gd_full``, one step kernel per measurement.
Status: SYMKF_ERR_DOMAIN (state unchanged) for Δt < 0 or β < 0, or for an initial sample that
does not determine an orientation; NaN inputs give SYMKF_ERR_NONFINITE.
"""
from __future__ import annotations

import casadi as ca

from symkf.models.base import Model
from ..discretize import continuous_dynamics, measurement_function
from ..model_functions import ModelFunctions, Symbols
from .framework import all_finite, make_kernel, register_family
from ..linalg import select
from ..spec import STATUS_DOMAIN, STATUS_NONFINITE, Family, FilterSpec, Kernel

#: A norm below this counts as zero (a zero-norm sample, a vanishing gradient).
ZERO_NORM = 1e-12

FORMS = ("simple", "full")
#: Measurements the family filters with, and their sizes: accelerometer; accelerometer + magnetometer.
MEASUREMENTS = {"imu": 3, "marg": 6}
#: ``Model.functions`` entry (x, m) -> q of measurement "marg": its parameters (the earth-field
#: reference) from the previous estimate x and the normalised magnetometer sample m.
EARTH_FIELD_REFERENCE = "earth_field_reference"
#: ``Model.functions`` entry (a, m) -> x: the orientation from one accelerometer and one
#: magnetometer sample (non-zero, not parallel).
INITIAL_ORIENTATION = "initial_orientation"


def check_model(model: Model) -> None:
    """ValueError (one line) unless ``model`` has what the family needs (module docstring)."""
    functions = model.functions
    wanted = [m for m in MEASUREMENTS if m in model.measurements]
    problems = []
    if model.nx != 4 or len(model.inputs) != 3 or [v.name for v in model.params] != ["beta", "alpha"]:
        problems.append("4 states (a scalar-last quaternion), 3 gyro inputs and params ['beta', 'alpha']")
    if not wanted or any(model.measurements[m].size != MEASUREMENTS[m] for m in wanted):
        problems.append(f"measurements 'imu' (3) and/or 'marg' (6), not {list(model.measurements)}")
    if ca.depends_on(model.f, model.t) or any(ca.depends_on(model.measurements[m].h, model.t) for m in wanted):
        problems.append("dynamics and measurements independent of t")
    for name in [INITIAL_ORIENTATION] + ([EARTH_FIELD_REFERENCE] if "marg" in wanted else []):
        if not isinstance(functions.get(name), ca.Function):
            problems.append(f"a CasADi Function Model.functions['{name}']")
    if problems:
        raise ValueError(f"filter family 'gradient_descent' needs {'; '.join(problems)} "
                         f"(as models/marg.py declares); model '{model.name}' has not")


def model_functions(model: Model) -> dict[str, ca.Function]:
    """The model's equations as the family uses them, shared by the kernels and the NumPy reference:
    ``quaternion_rate`` (x, u, p) -> q̇, ``gradient_<m>`` (x, u, p, q, z) -> Jᵀf of measurement m
    (``gradient_marg_gravity`` / ``gradient_marg_earth_field``: its accelerometer / magnetometer
    rows alone), and the model's own ``Model.functions``.

    ``q`` is scalar-last everywhere; gradients are ∂/∂q of the scalar-last q, i.e. the paper's
    gradient with its components reordered the same way.
    """
    check_model(model)
    opts = {"cse": True}
    x, u, p = ca.SX.sym("x", 4), ca.SX.sym("u", 3), ca.SX.sym("p", 2)
    f = continuous_dynamics(model)(0, x, u, p, ca.DM.zeros(len(model.noises)))
    made = {"quaternion_rate": ca.Function(f"{model.name}_quaternion_rate", [x, u, p], [f],
                                           ["x", "u", "p"], ["q_dot"], opts)}
    for name in MEASUREMENTS:
        if name not in model.measurements:
            continue
        q = ca.SX.sym("q", model.measurements[name].q.shape[0])
        h = measurement_function(model, name)(0, x, u, p, q)     # inlined: the kernels' CSE sees it
        parts = {name: range(MEASUREMENTS[name])}
        if name == "marg":
            parts.update(marg_gravity=range(3), marg_earth_field=range(3, 6))
        for part, rows in parts.items():
            z = ca.SX.sym("z", len(rows))
            objective = h[list(rows)] - z                   # (18), (22), (24): f = h(q) - z
            made[f"gradient_{part}"] = ca.Function(
                f"{model.name}_gradient_{part}", [x, u, p, q, z], [ca.jacobian(objective, x).T @ objective],
                ["x", "u", "p", "q", "z"], ["grad"], opts)      # (13): ∇f = Jᵀ f
    return {**made, **model.functions}


def unit_or_zero(v: ca.SX) -> tuple[ca.SX, ca.SX]:
    """(v/|v|, 1) for a usable sample, (0, 0) for a zero-norm one (never NaN). The norm is taken
    of v scaled by its largest component, so a huge finite sample cannot overflow to Inf."""
    largest = ca.fmax(ca.fabs(v[0]), ca.fmax(ca.fabs(v[1]), ca.fabs(v[2])))
    scaled = v / select(largest > 0, largest, 1)
    norm = ca.norm_2(scaled)
    ok = largest * norm > ZERO_NORM
    return scaled / select(ok, norm, 1), ok


def sample(z: ca.SX, mask: ca.SX, rows: slice) -> tuple[ca.SX, ca.SX]:
    """One vector sample of z, normalised, and its 0/1 flag: present (every mask entry > 0.5; a
    masked sample enters no arithmetic) and not zero-norm."""
    present = ca.SX(1)
    for i in range(rows.start, rows.stop):
        present = present * (mask[i] > 0.5)
    unit, ok = unit_or_zero(select(present, z[rows], ca.SX.zeros(3)))
    return unit, ok * present


def correction_direction(fns: dict, name: str, x, u, p, z, mask) -> tuple[ca.SX, ca.SX]:
    """Eq (27) normalised: ∇f/‖∇f‖ and a 0/1 flag that a correction exists (0 vector otherwise)."""
    a, acc_ok = sample(z, mask, slice(0, 3))
    if name == "imu":
        grad = select(acc_ok, fns["gradient_imu"](x, u, p, ca.SX(0, 1), a), ca.SX.zeros(4))
    else:
        m, mag_ok = sample(z, mask, slice(3, 6))
        b = fns[EARTH_FIELD_REFERENCE](x, m)
        grad = select(acc_ok, fns["gradient_marg_gravity"](x, u, p, b, a), ca.SX.zeros(4))
        grad = select(acc_ok * mag_ok, fns["gradient_marg"](x, u, p, b, ca.vertcat(a, m)),
                      select(mag_ok, fns["gradient_marg_earth_field"](x, u, p, b, m), grad))
    norm = ca.norm_2(grad)
    ok = norm > ZERO_NORM
    return grad / select(ok, norm, 1), ok


def filter_step(form: str, fns: dict, name: str, q: ca.SX, dt: ca.SX, u: ca.SX, p: ca.SX, z: ca.SX,
                mask: ca.SX) -> ca.SX:
    """One step of the full form (26)-(30) or the simplified form (31); returns q_est before it
    is normalised (the kernel checks its norm is finite and non-zero first)."""
    beta, alpha = p[0], p[1]
    q_dot = fns["quaternion_rate"](q, u, p)                           # (7)-(8)
    direction, corrected = correction_direction(fns, name, q, u, p, z, mask)   # (27), normalised
    if form == "simple":
        q_est = q + (q_dot - beta * direction) * dt                   # (31)
    elif form == "full":
        q_omega = q + q_dot * dt                                      # (9)
        rate_nabla = alpha * ca.norm_2(q_dot)                         # μ_t / Δt, (28)
        q_nabla = q - rate_nabla * dt * direction                     # (26)
        weight_sum = rate_nabla + beta
        gamma = select(corrected * (weight_sum > 0), beta / select(weight_sum > 0, weight_sum, 1), 0)   # (30)
        q_est = gamma * q_nabla + (1 - gamma) * q_omega               # (29)
    else:
        raise ValueError(f"form: expected one of {FORMS}, got {form!r}")
    return q_est


def step_kernel(symbols: Symbols, fns: dict, form: str, name: str) -> Kernel:
    s = symbols.sym
    msym, marg = symbols.measurement(name)
    z, mask = msym["z"], msym["mask"]
    beta = s["p"][0]
    q_est = filter_step(form, fns, name, s["x"], s["dt"], s["u"], s["p"], z, mask)
    norm = ca.norm_2(q_est)
    q_new = q_est / select(norm > ZERO_NORM, norm, 1)
    inputs = ["dt", "x", "u", "p", "z", "mask"]
    z_used = ca.vertcat(*[select(mask[i] > 0.5, z[i], 0) for i in range(z.shape[0])])
    finite = all_finite([s["x"], s["dt"], s["u"], z_used, s["p"]]) * (norm < ca.inf)
    status = select(finite, select((s["dt"] >= 0) * (beta >= 0) * (norm > ZERO_NORM), 0, STATUS_DOMAIN),
                    STATUS_NONFINITE)     # a huge sample overflows |q| to Inf: an error, never q = 0
    ok = status == 0
    equations = "(26)-(30)" if form == "full" else "(31)"
    sensors = "gyro + accelerometer + magnetometer" if name == "marg" else "gyro + accelerometer"
    return make_kernel(
        f"gd_{form}_{name}", f"Gradient-descent filter step, paper 001 eq {equations}, {sensors}; real dt per step.",
        symbols, msym, marg, inputs, [("x", select(ok, q_new, s["x"])), ("status", status)],
        carried=("x",), per_step=("dt", "u", "z", "mask"))


def initial_kernel(symbols: Symbols, fns: dict, name: str) -> Kernel:
    """Initial orientation from one sample z; 6-axis mode fixes the heading with a sensor axis instead of m."""
    msym, marg = symbols.measurement(name)
    z = msym["z"]
    a, acc_ok = unit_or_zero(z[0:3])
    if name == "marg":
        reference = z[3:6]
    else:       # any sensor axis not close to the vertical stands in for north
        reference = select(ca.fabs(a[0]) < 0.9, ca.DM([1.0, 0.0, 0.0]), ca.DM([0.0, 1.0, 0.0]))
    m, mag_ok = unit_or_zero(reference)
    ok = acc_ok * mag_ok * (ca.norm_2(ca.cross(a, m)) > 1e-6)
    q0 = fns[INITIAL_ORIENTATION](select(ok, a, ca.DM([0, 0, 1.0])), select(ok, m, ca.DM([1.0, 0, 0])))
    return make_kernel(f"gd_initial_{name}", "Initial orientation (TRIAD) from one accelerometer"
                       + (" and magnetometer" if name == "marg" else "") + " sample z.",
                       symbols, msym, marg, ["z"], [("x", q0), ("status", select(ok, 0, STATUS_DOMAIN))])


def kernels(model: Model, symbols: Symbols, functions: ModelFunctions) -> Family:
    """All gradient-descent kernels (a step kernel per form and measurement, an initial-orientation
    kernel per measurement) and the two filters ``gd_simple``, ``gd_full``: state x only, no
    predict, the samples as the measurement."""
    fns = model_functions(model)
    names = [m for m in MEASUREMENTS if m in model.measurements]
    steps = [step_kernel(symbols, fns, form, name) for form in FORMS for name in names]
    specs = [FilterSpec(f"gd_{form}", f"gd_{form}", "", {}, {name: f"gd_{form}_{name}" for name in names},
                        state=("x",), diagnostics=(), measurement_inputs=("z", "mask")) for form in FORMS]
    return Family(steps + [initial_kernel(symbols, fns, name) for name in names], specs)


register_family("gradient_descent", kernels, quaternions=True)      # a normalised quaternion

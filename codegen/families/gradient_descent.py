"""Gradient-descent MARG filter of paper 001 (Ryang, Kim 2020) as kernels: full form and simplified form.

One step, from the previous estimate q (scalar-last, unit) and the samples of one time instant:

- gyro: q̇_ω = ½ q ⊗ ω (7)-(8), q_ω = q + q̇_ω Δt (9);
- correction direction: ∇f/‖∇f‖ with ∇f = Jᵀ f (13), (27): f = f_g (18) in 6-axis mode (or when
  the magnetometer sample is zero), f = f_{g,b} (24) in 9-axis mode; J derived by CasADi from
  ``models/marg.py``. A zero-norm accelerometer sample drops f_g, a zero-norm magnetometer sample
  drops f_b; with neither (or ∇f = 0) the step is pure gyro integration: no NaN, q stays unit.
- full form (26)-(30): μ_t = α‖q̇_ω‖Δt, q_∇ = q - μ_t ∇f/‖∇f‖, γ_t = β / (μ_t/Δt + β),
  q_est = γ_t q_∇ + (1 - γ_t) q_ω; μ_t/Δt is evaluated as α‖q̇_ω‖ (no division by Δt);
- simplified form (31): q_est = q + (q̇_ω - β ∇f/‖∇f‖) Δt;
- both: q_est is normalised (the paper requires unit quaternions; (29) and (31) do not preserve it).

Kernels ("x" is the quaternion state [qx, qy, qz, qw], "p" = [beta, alpha] runtime parameters):
``gd_simple_imu``, ``gd_simple_marg``, ``gd_full_imu``, ``gd_full_marg`` (carried x, per-step dt,
u (gyro), acc, mag: so the generic C run loop filters a whole recording with the real Δt of every
sample), and ``gd_initial_marg`` / ``gd_initial_imu`` (orientation from the first sample).
Status: SYMKF_ERR_DOMAIN (state unchanged) for Δt < 0 or β < 0, or for an initial sample that
does not determine an orientation; NaN inputs give SYMKF_ERR_NONFINITE from the C wrapper.
"""
from __future__ import annotations

from functools import lru_cache

import casadi as ca

from symkf.models import marg as paper
from ..model_functions import ModelFunctions, Symbols
from .framework import all_finite, make_kernel, register_family
from ..linalg import select
from ..spec import STATUS_DOMAIN, STATUS_NONFINITE, Arg, Family, FilterSpec, Kernel

#: A norm below this counts as zero (a zero-norm sample, a vanishing gradient).
ZERO_NORM = 1e-12

FORMS = ("simple", "full")
MODES = ("imu", "marg")


@lru_cache(maxsize=1)
def marg_functions() -> dict[str, ca.Function]:
    """The model's equations as CasADi Functions, shared by the kernels and the NumPy reference.

    ``q`` is scalar-last everywhere; gradients are ∂/∂q of the scalar-last q, i.e. the paper's
    gradient with its components reordered the same way.
    """
    q, w, a, m, b = (ca.SX.sym(n, k) for n, k in (("q", 4), ("omega", 3), ("a", 3), ("m", 3), ("b", 3)))
    opts = {"cse": True}
    return {
        "quaternion_rate": ca.Function("marg_quaternion_rate", [q, w], [paper.quaternion_rate(q, w)],
                                       ["q", "omega"], ["q_dot"], opts),
        "gradient_gravity": ca.Function(
            "marg_gradient_gravity", [q, a], [paper.objective_gradient(paper.objective_gravity(q, a), q)],
            ["q", "a"], ["grad"], opts),
        "gradient_earth_field": ca.Function(
            "marg_gradient_earth_field", [q, b, m],
            [paper.objective_gradient(paper.objective_earth_field(q, b, m), q)], ["q", "b", "m"], ["grad"], opts),
        "gradient_stacked": ca.Function(
            "marg_gradient_stacked", [q, a, b, m],
            [paper.objective_gradient(paper.objective_stacked(q, a, b, m), q)], ["q", "a", "b", "m"], ["grad"], opts),
        "earth_field_reference": ca.Function("marg_earth_field_reference", [q, m],
                                             [paper.earth_field_reference(q, m)], ["q", "m"], ["b"], opts),
        "euler_angles": ca.Function("marg_sensor_euler_angles", [q], [paper.sensor_euler_angles(q)],
                                    ["q"], ["psi_theta_phi"], opts),
        "initial_orientation": ca.Function("marg_initial_orientation", [a, m], [paper.initial_orientation(a, m)],
                                           ["a", "m"], ["q"], opts),
    }


def unit_or_zero(v: ca.SX) -> tuple[ca.SX, ca.SX]:
    """(v/|v|, 1) for a usable sample, (0, 0) for a zero-norm one (never NaN). The norm is taken
    of v scaled by its largest component, so a huge finite sample cannot overflow to Inf."""
    largest = ca.fmax(ca.fabs(v[0]), ca.fmax(ca.fabs(v[1]), ca.fabs(v[2])))
    scaled = v / select(largest > 0, largest, 1)
    norm = ca.norm_2(scaled)
    ok = largest * norm > ZERO_NORM
    return scaled / select(ok, norm, 1), ok


def correction_direction(q: ca.SX, acc: ca.SX, mag: ca.SX | None) -> tuple[ca.SX, ca.SX]:
    """Eq (27) normalised: ∇f/‖∇f‖ and a 0/1 flag that a correction exists (0 vector otherwise)."""
    fns = marg_functions()
    a, acc_ok = unit_or_zero(acc)
    grad = select(acc_ok, fns["gradient_gravity"](q, a), ca.SX.zeros(4))
    if mag is not None:
        m, mag_ok = unit_or_zero(mag)
        b = fns["earth_field_reference"](q, m)
        grad = select(acc_ok * mag_ok, fns["gradient_stacked"](q, a, b, m),
                      select(mag_ok, fns["gradient_earth_field"](q, b, m), grad))
    norm = ca.norm_2(grad)
    ok = norm > ZERO_NORM
    return grad / select(ok, norm, 1), ok


def filter_step(form: str, q: ca.SX, dt: ca.SX, gyro: ca.SX, acc: ca.SX, mag: ca.SX | None,
                beta: ca.SX, alpha: ca.SX) -> ca.SX:
    """One step of the full form (26)-(30) or the simplified form (31); returns q_est before it
    is normalised (the kernel checks its norm is finite and non-zero first)."""
    q_dot = marg_functions()["quaternion_rate"](q, gyro)             # (7)-(8)
    direction, corrected = correction_direction(q, acc, mag)          # (27), normalised
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


def _args() -> tuple[dict, dict]:
    sym = {"acc": ca.SX.sym("acc", 3), "mag": ca.SX.sym("mag", 3)}
    arg = {"acc": Arg("acc", (3, 1), "any (normalised)", "accelerometer sample, sensor frame; zero = skip"),
           "mag": Arg("mag", (3, 1), "any (normalised)", "magnetometer sample, sensor frame; zero = skip")}
    return sym, arg


def step_kernel(symbols: Symbols, form: str, mode: str) -> Kernel:
    s = symbols.sym
    extra_sym, extra_arg = _args()
    beta, alpha = s["p"][0], s["p"][1]
    mag = extra_sym["mag"] if mode == "marg" else None
    q_est = filter_step(form, s["x"], s["dt"], s["u"], extra_sym["acc"], mag, beta, alpha)
    norm = ca.norm_2(q_est)
    q_new = q_est / select(norm > ZERO_NORM, norm, 1)
    inputs = ["x", "dt", "u", "acc"] + (["mag"] if mode == "marg" else []) + ["p"]
    finite = all_finite([s[i] if i in s else extra_sym[i] for i in inputs]) * (norm < ca.inf)
    status = select(finite, select((s["dt"] >= 0) * (beta >= 0) * (norm > ZERO_NORM), 0, STATUS_DOMAIN),
                    STATUS_NONFINITE)     # a huge sample overflows |q| to Inf: an error, never q = 0
    ok = status == 0
    equations = "(26)-(30)" if form == "full" else "(31)"
    sensors = "gyro + accelerometer + magnetometer" if mode == "marg" else "gyro + accelerometer"
    return make_kernel(
        f"gd_{form}_{mode}", f"Gradient-descent filter step, paper 001 eq {equations}, {sensors}; real dt per step.",
        symbols, extra_sym, extra_arg, inputs,
        [("x", select(ok, q_new, s["x"])), ("status", status)],
        carried=("x",), per_step=tuple(i for i in inputs if i in ("dt", "u", "acc", "mag")))


def initial_kernel(symbols: Symbols, mode: str) -> Kernel:
    """Initial orientation from one sample; 6-axis mode fixes the heading with a sensor axis instead of m."""
    extra_sym, extra_arg = _args()
    acc = extra_sym["acc"]
    a, acc_ok = unit_or_zero(acc)
    if mode == "marg":
        reference = extra_sym["mag"]
    else:       # any sensor axis not close to the vertical stands in for north
        reference = select(ca.fabs(a[0]) < 0.9, ca.DM([1.0, 0.0, 0.0]), ca.DM([0.0, 1.0, 0.0]))
    m, mag_ok = unit_or_zero(reference)
    ok = acc_ok * mag_ok * (ca.norm_2(ca.cross(a, m)) > 1e-6)
    q0 = marg_functions()["initial_orientation"](select(ok, a, ca.DM([0, 0, 1.0])), select(ok, m, ca.DM([1.0, 0, 0])))
    inputs = ["acc"] + (["mag"] if mode == "marg" else [])
    return make_kernel(f"gd_initial_{mode}", "Initial orientation (TRIAD) from one accelerometer"
                       + (" and magnetometer" if mode == "marg" else "") + " sample.",
                       symbols, extra_sym, extra_arg, inputs,
                       [("x", q0), ("status", select(ok, 0, STATUS_DOMAIN))])


def kernels(model, symbols: Symbols, functions: ModelFunctions) -> Family:
    """All gradient-descent kernels (4 step kernels, 2 initial-orientation kernels) and the four
    filters (form x mode) they make up: state x only, no predict, the samples as the measurement."""
    expected = (["qx", "qy", "qz", "qw"], 3, ["beta", "alpha"])
    found = (model.state_names(), len(model.inputs), [v.name for v in model.params])
    if found != expected:
        raise ValueError(f"filter family 'marg' needs states {expected[0]}, 3 gyro inputs and params "
                         f"{expected[2]} (as models/marg.py declares); model '{model.name}' has {found}")
    result = [step_kernel(symbols, form, mode) for form in FORMS for mode in MODES]
    specs = [FilterSpec(f"gd_{form}_{mode}", f"gd_{form}", "", {}, {mode: f"gd_{form}_{mode}"}, state=("x",),
                        diagnostics=(), measurement_inputs=("acc", "mag")) for form in FORMS for mode in MODES]
    return Family(result + [initial_kernel(symbols, mode) for mode in MODES], specs)


register_family("marg", kernels)

"""Multiplicative (error-state) EKF for any model with unit-quaternion states: family ``"mekf"``.

On the chart of ``chart.py`` and the shared pieces of ``manifold.py``.

**Prediction.** x̂⁻ = f_d(x̂) projected (q / |q|); P⁻ = F P Fᵀ + Q_d with
F = ∂/∂δ [f_d(x̂ ⊞ δ) ⊟ f_d(x̂)] at δ = 0, derived by CasADi through the retraction (or, with
manifold_transition="series", the series I + A dt + (A dt)²/2 of the continuous error dynamics
A = ∂δ̇/∂δ, also derived by CasADi: :meth:`ManifoldFunctions.error_rate_matrix`); Q_d as in ``manifold.py``.

**Update (MEKF).** H = ∂h(x̂ ⊞ δ)/∂δ at δ = 0 (CasADi); with S = L Lᵀ and U = L⁻¹ H P,
δ̂ = K y = Uᵀ L⁻¹ y and P⁺ = P - K S Kᵀ = P - Uᵀ U (lower triangle, mirrored); then
the multiplicative reset x̂⁺ = x̂ ⊞ δ̂ (quaternion renormalised against round-off). The
covariance is *not* transported to the reset point (the first-order reset of Lefferts, Markley &
Shuster 1982, as in paper 000); the omitted term is O(|δθ̂| P). With ``manifold_update="sequential"``
the same update is m scalar updates in turn (:func:`sequential_update`; a diagonal R). The step
kernel is one expression (:func:`mekf_step_kernel`): inputs checked once, outputs selected once.

**Iterated update.** ``mekf_iterations`` > 1 (:class:`~symkf.codegen.families.iterated.MekfIteratedOptions`):
Gauss-Newton iterations of the batch update, relinearised at x̂ ⊞ δᵢ (:func:`iterated_correction`).

**Run variants.** ``manifold_run_variants`` (:class:`MekfOptions`) lists mask patterns that get
MEKF step and run kernels of their own, the masked components and the gate folded away
(:func:`mekf_run_kernels`; the same results, a larger bundle).

Masks, gates, status codes and input checks: ``manifold.py``.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import ClassVar

import casadi as ca

from symkf.models.base import Model
from .. import linalg
from ..discretize import FUNCTION_OPTIONS
from ..model_functions import ModelFunctions, Symbols
from ..spec import CodegenConfig, ConfigError, Family, Kernel, option
from .chart import ManifoldOptions
from .framework import CANONICAL_ORDER, filter_spec, make_kernel, masked_noise, register_family
from .iterated import MekfIteratedOptions, iterations, prior_sigmas
from .kalman import UPDATE_INPUTS, _predict_doc
from .rts import smooth_kernel
from .manifold import (ManifoldFunctions, ManifoldSymbols, chart_innovation, error_process_noise, measurement_input,
                       predict_kernel, predict_status, require_quaternion, update_outputs)


@dataclass(frozen=True)
class MekfOptions:
    """The MEKF's own codegen option (beside :class:`~symkf.codegen.families.chart.ManifoldOptions`)."""

    run_variants: tuple = option((), "mask patterns (each a tuple of the measurement components masked to 0) "
                                     "that get MEKF step and run kernels of their own, those updates folded away: "
                                     "the same results, a larger bundle; e.g. ((3,), (4, 5, 6))")

    prefix: ClassVar[str] = "manifold_"


def run_variants(model: Model, config: CodegenConfig, name: str, size: int) -> list[tuple[int, ...]]:
    """The mask patterns of measurement ``name`` (``size`` mask entries) that get their own run
    kernel (codegen option ``manifold_run_variants``: a sequence of sets of mask entries, e.g.
    ``((3,), (4, 5, 6))``; default none), largest first: :func:`mekf_run_kernels`."""
    patterns = []
    for pattern in config.get("manifold_run_variants", ()) or ():
        entries = tuple(sorted({int(i) for i in pattern}))
        if any(i < 0 or i >= size for i in entries):
            raise ConfigError(f"model '{model.name}': manifold_run_variants {pattern!r}: measurement '{name}' has "
                              f"{size} components")
        patterns.append(entries)
    return sorted(set(patterns), key=lambda e: (-len(e), e))


# ---------------------------------------------------------------------- MEKF
def mekf_update_expr(mf: ManifoldFunctions, ms: ManifoldSymbols, name: str, msym: dict, wrap, state=None,
                     trusted: bool = False):
    """The MEKF update of x̂, P at t (the kernel's inputs), or of ``state`` = (t, x, P) of a fused
    step: a predicted P, exactly symmetric, whose PSD and finiteness need no check of their own
    (checked in the step's input; a result that overflows is refused by the backends' output
    checks; if the prediction failed, the step's outputs are its inputs and y, S are not read).
    Batch or sequential (:class:`ManifoldOptions`); ``trusted``: R's diagonal is not tested (a run's
    trusted kernel, :func:`mekf_run_kernels`)."""
    s = ms.base.sym
    t, x, P = state or (s["t"], s["x"], ms.sym["P"])
    m = measurement_input(mf.model, ms, name, msym)
    z_pred = mf.h_inline[name](t, x, s["u"], s["p"], msym["q"])
    folded = {i for pattern in run_variants(mf.model, mf.fns.config, name, msym["mask"].numel()) for i in pattern}
    H = masked_rows(m.mask, mf.jac_h[name](t, x, s["u"], s["p"], msym["q"]), folded)
    y = chart_innovation(mf, name, m, z_pred, wrap)
    HPH = linalg.sandwich(H, P)                      # sparse H: structural zeros cost nothing
    if _sequential(mf, name):
        if iterations(mf.fns.config, MekfIteratedOptions) > 1:
            raise ConfigError("mekf_iterations > 1 iterates the batch update; it cannot be combined with "
                              "manifold_update='sequential'")
        # R must be diagonal (else SYMKF_ERR_ARGS, outputs not written): its masked diagonal only
        r = [msym["R"][i, i] * m.mask[i] * m.mask[i] + (1 - m.mask[i]) for i in range(H.shape[0])]
        S = linalg.symmetric(len(r), lambda i, j: HPH[i, j] + (r[i] if i == j else 0))
        correction, P_new, nis, ok = sequential_update(H, P, y, r, symmetric=state is not None)
        m.valid = 1 if trusted else diagonal_flag(msym["R"])
    else:
        R = masked_noise(mf.measurement_noise(name, msym["R"], t, x, s["u"], s["p"], msym["q"]), m.mask)
        S = linalg.symmetric(R.shape[0], lambda i, j: HPH[i, j] + linalg.symmetric_part(R, i, j))
        correction, P_new, nis, ok = batch_update(H, P, y, S)
        if iterations(mf.fns.config, MekfIteratedOptions) > 1:
            correction, P_new, ok = iterated_correction(mf, name, msym, m, wrap, (t, x, P, s["u"], s["p"]),
                                                        correction, P_new, ok, folded)
    ok = ok if state is not None else ok * linalg.psd_flag(P)
    x_new = mf.retract(x, correction)               # multiplicative reset
    return (x_new, P_new, y, S, ok, nis, m.finite, mf.chart.in_domain(correction)), m


def iterated_correction(mf: ManifoldFunctions, name: str, msym: dict, m, wrap, state, delta, P_new, ok, folded):
    """Gauss-Newton iterations of the batch update (option ``mekf_iterations``, iterated.py): from
    delta_1 = K y, relinearise at x_i = x (+) delta_i: y_i = z (-) h(x_i), H_i = dh(x_i (+) e)/de,
    delta_{i+1} = K_i (y_i + H_i delta_i), P+ = P - K_i S_i K_i^T. H_i is taken in x_i's own chart,
    which differs from the prior's by O(|delta_i|), the order the first-order reset already drops.
    Stops, in effect, once delta moves by no more than the tolerance (in prior sigmas)."""
    options = MekfIteratedOptions.of(mf.fns.config)
    t, x, P, u, p = state
    sigma = prior_sigmas(P)
    active = ca.SX(1)
    previous = ca.SX.zeros(delta.shape)
    for _ in range(options.iterations - 1):
        active = active * options.still_moving(delta, previous, sigma)
        x_i = mf.retract(x, delta)
        q = msym["q"]
        H = masked_rows(m.mask, mf.jac_h[name](t, x_i, u, p, q), folded)
        y = chart_innovation(mf, name, m, mf.h_inline[name](t, x_i, u, p, q), wrap)
        R = masked_noise(mf.measurement_noise(name, msym["R"], t, x_i, u, p, q), m.mask)
        HPH = linalg.sandwich(H, P)
        S = linalg.symmetric(R.shape[0], lambda i, j: HPH[i, j] + linalg.symmetric_part(R, i, j))
        step, P_step, _, ok_step = batch_update(H, P, y + H @ delta, S)
        previous = delta
        delta = linalg.select(active, step, delta)
        P_new = linalg.select(active, P_step, P_new)
        ok = ok * linalg.select(active, ok_step, 1)
    return delta, P_new, ok


def masked_rows(mask, J, guarded=()) -> ca.SX:
    """diag(mask) J, the rows in ``guarded`` exactly 0 when masked even where J is not finite (e.g.
    the heading's H with no horizontal field: 0 * Inf): their entries are clamped to ±BIG first
    (NaN -> -BIG; fmin/fmax, which CasADi does not push into later products as it does an
    if_else). The guarded rows are those a kernel variant folds away (``manifold_run_variants``),
    so that the general kernel (VM backend, a run's first or gated steps) ignores a masked row as
    the variant does; a used row with a non-finite entry stays refused. Sparse."""
    H = ca.SX(J)
    rows, cols = J.sparsity().get_triplet()
    for i, j in zip(rows, cols):
        H[i, j] = mask[i] * (ca.fmin(ca.fmax(J[i, j], -BIG), BIG) if i in guarded else J[i, j])
    return H


#: The clamp of :func:`masked_rows` (finite, and far above any derivative a filter can use).
BIG = 1e300


def _sequential(mf: ManifoldFunctions, name: str) -> bool:
    meas = mf.model.measurements[name]
    return mf.options.update == "sequential" and not meas.quaternion and name not in mf.noise_jac


def batch_update(H, P, y, S):
    """With S = L Lᵀ and U = L⁻¹ H P: δ̂ = K y = Uᵀ L⁻¹ y and P⁺ = P - K S Kᵀ = P - Uᵀ U (lower
    triangle, mirrored), as the Kalman EKF and UKF. Returns δ̂, P⁺, yᵀ S⁻¹ y and the Cholesky flag."""
    L, ok = linalg.cholesky(S)
    U = linalg.solve_lower(L, H @ P)
    white = linalg.solve_lower(L, y)
    UtU = linalg.gram(U)
    P_new = linalg.symmetric(P.shape[0], lambda i, j: linalg.symmetric_part(P, i, j) - UtU[i, j])
    return U.T @ white, P_new, ca.sumsqr(white), ok


def sequential_update(H, P, y, r, symmetric: bool = False):
    """The same update as :func:`batch_update` for a diagonal R, as m scalar updates in turn
    (Maybeck, "Stochastic Models, Estimation and Control" Vol. 1, 1979, sec. 7.7; exact in exact
    arithmetic, both linearised at the prior): per component i, with the correction δ so far,
    s_i = hᵢ P hᵢᵀ + R_ii, k = P hᵢᵀ / s_i, δ += k (y_i - hᵢ δ), P -= k (P hᵢᵀ)ᵀ (lower triangle).
    The s_i are the pivots of S = H P Hᵀ + R (its LDLᵀ), so all s_i > 0 is the batch's Cholesky
    flag, and Σ (y_i - hᵢ δ)² / s_i = yᵀ S⁻¹ y. A masked row (hᵢ = 0, y_i = 0, r_i = 1) changes nothing.
    ``r``: the diagonal of R; ``symmetric``: P is exactly symmetric (else its symmetric part is used)."""
    n = P.shape[0]
    P = P if symmetric else linalg.symmetric(n, lambda i, j: linalg.symmetric_part(P, i, j))
    delta, nis, ok = ca.SX.zeros(n), ca.SX(0), ca.SX(1)
    for i in range(H.shape[0]):
        h = H[i, :]
        Ph = P @ h.T
        s = ca.dot(h.T, Ph) + r[i]
        usable = (s > 0) * (s < ca.inf)
        ok = ok * usable
        inverse = 1 / linalg.guarded(s, usable)
        residual = y[i] - ca.dot(h.T, delta)
        gain = Ph * inverse
        delta = delta + gain * residual
        nis = nis + residual * residual * inverse
        P = linalg.symmetric(n, lambda a, b, P=P, gain=gain, Ph=Ph: P[a, b] - gain[a] * Ph[b])
    return delta, P, nis, ok


def diagonal_flag(R) -> ca.SX:
    """1 if the symmetric part of R (the one a batch update uses) is diagonal, else 0: a sequential
    update needs uncorrelated components."""
    flag = ca.SX(1)
    for i in range(R.shape[0]):
        for j in range(i):
            flag = flag * (R[i, j] + R[j, i] == 0)
    return flag


def mekf_kernels(model: Model, symbols: Symbols, fns: ModelFunctions) -> Family:
    require_quaternion(model, "mekf")
    mf, ms = ManifoldFunctions(model, fns), ManifoldSymbols(model, symbols)
    s, P = symbols.sym, ms.sym["P"]
    x_pred, P_pred = mekf_predict_expr(model, mf, ms)
    doc = _predict_doc(model, "Multiplicative EKF", f"{_step_words(mf)} then |q| = 1; P = F P F^T + Q_d, "
                       "F = d(f_d(x (+) d) (-) f_d(x))/dd in error coordinates")
    predict = predict_kernel("mekf_predict", doc, ms, mf, x_pred, P_pred, linalg.psd_flag(P), PREDICT_INPUTS)
    kernels = [predict]
    for name, meas in model.measurements.items():
        msym, marg = ms.measurement(name)
        upd, m = mekf_update_expr(mf, ms, name, msym, meas.wrap)
        update = make_kernel(
            f"mekf_update_{name}", f"Multiplicative EKF update with '{name}': H = dh(x (+) d)/dd, P - K S K^T, "
            "reset x = x (+) K y (masked, gated).", symbols, msym, marg, UPDATE_INPUTS,
            update_outputs(mf.chart, upd, s["x"], P, msym, m))
        step = mekf_step_kernel(model, mf, ms, name, predict, update, (x_pred, P_pred))
        run = mekf_run_kernels(model, mf, ms, name, predict, update, step, (x_pred, P_pred))
        step, step_variants = with_variants(model, mf, name, step, step.name)
        kernels += [update, step, *run, *step_variants]
    run = {name: f"mekf_run_{name}" for name in model.measurements}
    kernels.append(mekf_smooth_kernel(model, mf, ms))
    return Family(kernels, [filter_spec("mekf", "manifold_ekf", kernels, model.measurements, run=run,
                                        smooth="mekf_smooth")])


def mekf_run_kernels(model: Model, mf: ManifoldFunctions, ms: ManifoldSymbols, name: str, predict: Kernel,
                     update: Kernel, step: Kernel, predicted) -> list[Kernel]:
    """``mekf_run_<m>`` (:func:`run_kernel`) and its trusted partner ``mekf_run_<m>_trusted``, the
    kernel the C run loop iterates once a step has succeeded (``Kernel.trusted``): the carried
    x, P are then the filter's own output and R passed the step's test, so it leaves out

    - |q| = 1 of the input x: a step's x is renormalised (q / |q|, finite: checked on output);
    - R diagonal (sequential update): R is fixed along a run, and a step that succeeded had it so;
    - the PSD test of the input P (:func:`linalg.psd_flag`, 0.23k of the kernel's 2.1k operations
      for n_e = 6): P is F P Fᵀ + Q_d of a P that passed it, then scalar updates with positive
      pivots, PSD in exact arithmetic; its round-off (~1e-16 relative) is far inside the test's
      tolerance (:data:`linalg.PSD_TOLERANCE` = 1e-9 on the correlation matrix). This is the one
      check a run does not repeat that step-by-step calls do: only a P that fails the test after
      a successful step (none seen) would be coded differently (the step: NOT_PD, the run: the
      update's own code).

    The same expressions otherwise: x, P and codes bit-identical to the checked kernel's.

    With the codegen option ``manifold_run_variants`` (:func:`run_variants`), the trusted kernel
    also comes in one variant per listed mask pattern, ``mekf_run_<m>_masked_<i>_<j>...`` (the
    empty pattern: ``mekf_run_<m>_ungated``): the gate and the listed mask entries replaced by the
    constant 0, so CasADi removes what they multiply away: the masked components' scalar updates,
    their h and H rows (the heading's atan2), the gate's test and selects. The loop calls one when
    the run's gate is off (all 0) and the step's listed mask entries are exactly 0 (``Kernel.variants``).
    A masked component's scalar update changes nothing (hᵢ = 0: P - 0, δ + 0, NIS + 0; the gain's
    pivot is 1), so a variant gives the trusted kernel's x, P and codes (up to the sign of a zero)."""
    run = run_kernel(step)
    unchecked = mekf_step_kernel(model, mf, ms, name, predict, update, predicted, trusted=True)
    trusted, variants = with_variants(model, mf, name, run_kernel(unchecked, f"{run.name}_trusted", carried=()),
                                      run.name)
    return [replace(run, trusted=trusted.name), trusted, *variants]


def with_variants(model: Model, mf: ManifoldFunctions, name: str, kernel: Kernel, base: str):
    """``kernel`` with its ``variants`` (``Kernel.variants``: one per pattern of
    ``manifold_run_variants``, :func:`masked_variant`) and those variant kernels."""
    patterns = run_variants(model, mf.fns.config, name, kernel.inputs[kernel.input_index("mask")].size)
    variants = [masked_variant(kernel, base, entries) for entries in patterns]
    gate = tuple(range(kernel.inputs[kernel.input_index("gate")].size))
    conditions = tuple((v.name, (("gate", gate), ("mask", entries))) for v, entries in zip(variants, patterns))
    return replace(kernel, variants=conditions), variants


def masked_variant(kernel: Kernel, base: str, entries: tuple[int, ...]) -> Kernel:
    """``kernel`` with the gate and the mask entries ``entries`` set to the constant 0: named
    ``<base>_masked_<i>_<j>...`` (``<base>_ungated`` for no entry)."""
    f = kernel.function
    inputs = f.sx_in()
    gate, mask = inputs[kernel.input_index("gate")], inputs[kernel.input_index("mask")]
    fixed = [gate[i] for i in range(gate.numel())] + [mask[i] for i in entries]
    outputs = ca.substitute(f.call(inputs), [ca.vertcat(*fixed)], [ca.DM.zeros(len(fixed))])
    name = f"{base}_masked_{'_'.join(map(str, entries))}" if entries else f"{base}_ungated"
    function = ca.Function(f"{f.name().split('_k_')[0]}_k_{name}", inputs, outputs, f.name_in(), f.name_out(),
                           FUNCTION_OPTIONS)
    what = f"mask entries {list(entries)} and the gate 0" if entries else "the gate 0 (off)"
    return Kernel(name, function, f"{kernel.doc} Specialised for {what}: called for it by the wrapper "
                  f"of {kernel.name} and by the run loop.", kernel.inputs, kernel.outputs, (), kernel.per_step)


def run_kernel(step: Kernel, name: str = "", carried=None) -> Kernel:
    """``mekf_run_<measurement>``: the fused step without its diagnostics y and S, the kernel the C
    run loop iterates (``FilterSpec.run``): a run keeps only x, P and the status of each step, so
    CasADi drops what only y and S need (the S matrix: ~0.25k of the MARG step's ~2.3k operations)
    and the loop neither checks nor copies them. x, P and the status are the step's own expressions:
    the same numbers and codes, except that the step wrapper also refuses a step whose y or S
    output is not finite (SYMKF_ERR_NONFINITE) and the run does not look at them."""
    f = step.function
    keep = [i for i in range(f.n_out()) if f.name_out(i) in (*step.carried, "status")]
    name = name or step.name.replace("mekf_step_", "mekf_run_")
    function = ca.Function(f"{f.name().split('_k_mekf_step_')[0]}_k_{name}", f.sx_in(),
                           [f.call(f.sx_in())[i] for i in keep], f.name_in(), [f.name_out(i) for i in keep],
                           FUNCTION_OPTIONS)
    what = "the step the run loop iterates" if carried is None else \
        "the step the run loop iterates once a step has succeeded (no test of |q|, P PSD or R diagonal)"
    return Kernel(name, function, f"{step.doc} Without the diagnostics y, S: {what}.", step.inputs,
                  tuple(step.outputs[i] for i in keep), step.carried if carried is None else tuple(carried),
                  step.per_step)


PREDICT_INPUTS = ["t", "dt", "x", "P", "u", "p", "Q"]


def mekf_predict_expr(model: Model, mf: ManifoldFunctions, ms: ManifoldSymbols):
    """x̂⁻ = f_d(x̂) projected, P⁻ = F P Fᵀ + Q_d (lower triangle, mirrored)."""
    return mekf_prediction(model, mf, ms)[:2]


def mekf_prediction(model: Model, mf: ManifoldFunctions, ms: ManifoldSymbols):
    """:func:`mekf_predict_expr` and the error-state F (the smoother's cross-covariance is P Fᵀ)."""
    s, P, Q = ms.base.sym, ms.sym["P"], ms.sym["Q"]
    x_pred, F = mf.step_and_jac(s["t"], s["dt"], s["x"], s["u"], s["p"])
    FPF, Qd = linalg.sandwich(F, P), error_process_noise(model, mf, ms.base, Q, s["x"], s["t"], s["dt"])
    return x_pred, linalg.symmetric(P.shape[0], lambda i, j: FPF[i, j] + linalg.symmetric_part(Qd, i, j)), F


def mekf_smooth_kernel(model: Model, mf: ManifoldFunctions, ms: ManifoldSymbols) -> Kernel:
    """The error-state RTS backward step (codegen/families/rts.py on the chart): D = P Fᵀ,
    x^s_k = x_k ⊞ G (x^s_{k+1} ⊟ x̂⁻)."""
    P = ms.sym["P"]
    x_pred, P_pred, F = mekf_prediction(model, mf, ms)
    return smooth_kernel("mekf_smooth", "Multiplicative EKF RTS smoother: one backward step from step k + 1 to k "
                         "in error coordinates (G = P F^T (P-)^-1, x = x (+) G (xs (-) x-)).", ms.base, ms.sym, ms.arg,
                         PREDICT_INPUTS, (x_pred, P_pred, P @ F.T, linalg.psd_flag(P)), chart=mf.chart,
                         domain=mf.chart.unit_norm(ms.base.sym["x"]))


def mekf_step_kernel(model: Model, mf: ManifoldFunctions, ms: ManifoldSymbols, name: str, predict: Kernel,
                     update: Kernel, predicted, trusted: bool = False) -> Kernel:
    """Predict then update at t + dt as ONE expression (same results and codes as
    ``framework.compose_step`` of the two kernels): the inputs are checked once (|q| = 1, P PSD; their
    finiteness by the callers), the predicted P needs no PSD check of its own (F P Fᵀ + Q_d of a PSD
    P), the update works on the predicted x, P directly, and x, P are selected only by the gate (a
    failed step's outputs are not written: :func:`update_outputs`). ``trusted``: without the tests
    of |q| = 1, P PSD and R diagonal (:func:`mekf_run_kernels`)."""
    s, P = ms.base.sym, ms.sym["P"]
    msym, marg = ms.measurement(name)
    status_pred = predict_status(mf, ms.base, 1 if trusted else linalg.psd_flag(P), unit=not trusted)
    x1, P1 = predicted          # if the prediction failed, the outputs below are the inputs
    upd, m = mekf_update_expr(mf, ms, name, msym, model.measurements[name].wrap, state=(s["t"] + s["dt"], x1, P1),
                              trusted=trusted)
    outputs = dict(update_outputs(mf.chart, upd, x1, P1, msym, m))
    failed = status_pred != 0
    outputs["status"] = linalg.select(failed, status_pred, outputs["status"])   # x, P: not written then
    inputs = sorted(set(PREDICT_INPUTS) | set(UPDATE_INPUTS), key=CANONICAL_ORDER.index)
    doc = (f"{predict.doc.split(' (')[0]}; then {update.doc.replace(' at time t ', ' at t + dt ')} "
           "Both in one call.")
    return make_kernel(f"mekf_step_{name}", doc, ms.base, msym, marg, inputs, list(outputs.items()),
                       carried=("x", "P"), per_step=tuple(i for i in inputs if i in ("t", "dt", "u", "q", "z", "mask")))


def _step_words(mf: ManifoldFunctions) -> str:
    return "the model's exact step" if mf.options.step == "exact" else "RK4"


register_family("mekf", mekf_kernels, quaternions=True, options=(ManifoldOptions, MekfOptions, MekfIteratedOptions))

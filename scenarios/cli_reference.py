"""What ``symkf`` can tell a user about the installed package: its version, the paper models, the
codegen options (``symkf options``) and the filter families (``symkf families``).

Every listing is read from the code that defines it: the version from the package metadata, the
models' descriptions from their files' docstrings, the options from their declarations
(:func:`symkf.codegen.spec.codegen_options`), the family names from the family registry. Only the
families' short guide (:data:`FAMILY_GUIDE`: what each assumes and what x0, P0 and Q mean for it)
is written here, and a test holds its names to the family registry
(``symkf.codegen.families.framework.FAMILIES``), so a new family without a guide entry fails.
"""
from __future__ import annotations

import ast
import textwrap
from dataclasses import dataclass

import symkf
from symkf.codegen.spec import Option, codegen_options
from symkf.models import MODELS_DIR, PAPER_MODELS


@dataclass(frozen=True)
class FamilyGuide:
    """A user's summary of one filter family (``Model.filters`` names it)."""

    filters: str          #: the filter names it makes (``CompiledModel.filter(name, ...)``)
    summary: str          #: what it is and what it assumes
    x0: str               #: what the initial state holds
    P0: str               #: what the initial covariance is, in which coordinates and units
    Q: str                #: what the process-noise argument is
    cost: str             #: the work per step, in the model's sizes


_ERROR_P0 = ("covariance in error coordinates, n_error x n_error (Model.n_error = n - one per "
             "quaternion): three entries per quaternion, a rotation vector in rad with the default chart "
             "(manifold_chart='rotation_vector', body-frame error q = q^ * Exp(dtheta)), or the vector part "
             "of the error quaternion (half-angle units) with manifold_chart='vector_part'; one entry per "
             "ordinary state in its own unit squared")
_QUATERNION_X0 = "the full state, each quaternion as four numbers [x, y, z, w] (scalar-last, unit norm)"
_KALMAN_Q = ("power spectral density: n x n of an additive noise on every state (Q_d = Q dt), or, for a "
             "model that declares noise(), nw x nw of those noises (Q_d = G Q G^T dt, G = df/dw at the step start)")

#: The families a model can list in ``Model.filters``, for ``symkf families`` and the docs.
FAMILY_GUIDE: dict[str, FamilyGuide] = {
    "ekf": FamilyGuide(
        "ekf", "extended Kalman filter: RK4 step f_d cut at the model's events, F = df_d/dx derived "
        "by CasADi, Joseph-form update; any model",
        "n states in the model's units", "n x n covariance of x (each state's unit squared)", _KALMAN_Q,
        "one f_d with its Jacobian, one update (m x m solve)"),
    "ukf": FamilyGuide(
        "ukf", "unscented Kalman filter: 2n + 1 Julier sigma points (scalar kappa, default 0; n + kappa > 0), "
        "angle outputs averaged on the circle; any model",
        "n states in the model's units", "n x n covariance of x (each state's unit squared)", _KALMAN_Q,
        "2n + 1 evaluations of f_d and of h, two n x n Cholesky factors"),
    "srekf": FamilyGuide(
        "srekf", "square-root EKF (array form): the lower Cholesky factor L of P carried, predicted by a QR "
        "of [F L, sqrt(Q_d)], updated by triangularising the pre-array; the EKF's numbers; any model",
        "n states in the model's units", "n x n covariance of x, given and read as P (Filter.factor reads L)",
        _KALMAN_Q, "two QR factorisations of (n + m) x (2n + m) arrays"),
    "srukf": FamilyGuide(
        "srukf", "square-root UKF (Van der Merwe & Wan 2001): L carried, QR of the weighted sigma-point "
        "deviations and rank-one Cholesky updates / downdates; the UKF's numbers, a semi-definite P0 accepted",
        "n states in the model's units", "n x n covariance of x, given and read as P (Filter.factor reads L)",
        _KALMAN_Q, "2n + 1 evaluations of f_d and of h, one QR and m + 1 rank-one updates"),
    "cd_ekf": FamilyGuide(
        "cd_ekf", "continuous-discrete EKF: x and P integrated together by RK4 (P' = A P + P A^T + Q), "
        "discrete updates at each sensor's rate; any model",
        "n states in the model's units", "n x n covariance of x (each state's unit squared)",
        "n x n power spectral density of an additive noise on every state (G = I)",
        "RK4 of x and the upper triangle of P, sparse A; update O(n^2 m)"),
    "srcdekf": FamilyGuide(
        "srcdekf", "square-root continuous-discrete EKF: x, Phi' = A Phi and Q_d' = A Q_d + Q_d A^T + Q by RK4, "
        "then L = qr[Phi L, chol(Q_d)] per sub-step; the array-form update; the CD-EKF's numbers; any model",
        "n states in the model's units", "n x n covariance of x, given and read as P (Filter.factor reads L)",
        "n x n power spectral density of an additive noise on every state (G = I)",
        "RK4 of x, Phi (n x n) and Q_d, an n x n Cholesky and a QR of an n x 2n array per sub-step; "
        "update a QR of an (n + m)-row array"),
    "mekf": FamilyGuide(
        "mekf", "multiplicative (error-state) EKF for a model with quaternion_state(): F and H derived "
        "through the chart, multiplicative reset after each update",
        _QUATERNION_X0, _ERROR_P0,
        "power spectral density in error coordinates: n_error x n_error additive, or nw x nw of the "
        "model's noise() (manifold_noise='held': held over the step, paper 000 eq (29))",
        "one f_d with its Jacobian through the chart, one update (or m scalar updates: "
        "manifold_update='sequential')"),
    "srmekf": FamilyGuide(
        "srmekf", "square-root multiplicative EKF: the MEKF carrying the lower Cholesky factor of the error "
        "covariance, predicted by a QR of [F L, sqrt(Q_d)], updated by triangularising the pre-array, then the "
        "multiplicative reset; the MEKF's numbers",
        _QUATERNION_X0, _ERROR_P0 + "; given and read as P (Filter.factor reads L)", "as mekf",
        "one f_d with its Jacobian through the chart, two QR factorisations of (n_error + m)-row arrays"),
    "mukf": FamilyGuide(
        "mukf", "manifold UKF for a model with quaternion_state(): sigma points through the retraction, "
        "quaternion mean by the eigenvector method, additive noise",
        _QUATERNION_X0, _ERROR_P0, "as mekf",
        "2 n_error + 1 evaluations of f_d and h, a 4 x 4 quaternion mean per quaternion"),
    "sukf": FamilyGuide(
        "sukf", "paper 000's UKF with separated noise spaces: process noise sampled with the propagation's "
        "sigma points, measurement noise (Model.measurement_noise) with the update's",
        _QUATERNION_X0, _ERROR_P0,
        "nw x nw power spectral density of the model's process noises w, sampled as Q/dt (no additive Q)",
        "2(n_error + nw) + 1 propagations, 2(n_error + nv) + 1 measurement evaluations"),
    "aukf": FamilyGuide(
        "aukf", "paper 000's fully augmented UKF in [dx, w, v]: one Cholesky factor of blockdiag(P, Q/dt, R) "
        "per step; a model with one measurement",
        _QUATERNION_X0, _ERROR_P0, "as sukf",
        "2(n_error + nw + nv) + 1 sigma points, one full Cholesky factor"),
    "gradient_descent": FamilyGuide(
        "gd_simple, gd_full", "gradient-descent (Madgwick-type) attitude filter of paper 001: gyro "
        "integration corrected along the normalised gradient of the accelerometer (and magnetometer) "
        "residual; a model with a quaternion state, a gyro input u and parameters beta, alpha",
        "the quaternion [x, y, z, w] (scalar-last, unit norm)",
        "none: the filter carries no covariance (leave P0 out)", "none: the gain is the parameter beta (p)",
        "one gradient of h, no matrix factorisation"),
}


def version_text() -> str:
    """``symkf --version``: the installed version, and CasADi's (it is part of every build's hash)."""
    import casadi
    return f"symkf {symkf.__version__} (CasADi {casadi.__version__})"


def model_descriptions() -> dict[str, str]:
    """{short name: first line of the model file's docstring} of the paper models (files read, not run)."""
    out = {}
    for name in PAPER_MODELS:
        doc = ast.get_docstring(ast.parse((MODELS_DIR / f"{name}.py").read_text(encoding="utf-8"))) or ""
        out[name] = " ".join(doc.split("\n\n")[0].split())
    return out


def models_text(width: int = 100) -> str:
    """The models ``symkf build`` accepts, for its ``--help``."""
    found = model_descriptions()
    pad = max(map(len, found)) + 2
    lines = textwrap.wrap("models: a paper model's short name, a .py file whose build() returns a Model "
                          "(path/to/tracker.py), or an importable module (mypkg.tracker)", width)
    for name, text in found.items():
        lines += textwrap.wrap(text, width, initial_indent=f"  {name:<{pad}}", subsequent_indent=" " * (pad + 2))
    lines += ["", "codegen options for --set KEY=VALUE: symkf options"]
    return "\n".join(lines)


def _default(option: Option) -> str:
    return "derived (see meaning)" if option.default is None else repr(option.default)


def options_text(width: int = 100) -> str:
    """``symkf options``: every codegen option with its type, default and meaning."""
    lines = ["codegen options: symkf build MODEL --set KEY=VALUE, load(MODEL, KEY=VALUE), or a model's "
             "Model.codegen_defaults; each configuration builds into a folder of its own", ""]
    for option in codegen_options():
        lines.append(f"{option.name}  ({option.type_name}, default {_default(option)})")
        lines += textwrap.wrap(option.meaning, width, initial_indent="    ", subsequent_indent="    ")
    return "\n".join(lines)


def options_markdown() -> str:
    """The codegen options reference page of the documentation (``symkf options --markdown``)."""
    lines = ["# Codegen options", "",
             "Generated by `symkf options --markdown` from the option declarations in the code; a test keeps "
             "this page equal to that output.", "",
             "Set an option with `symkf build MODEL --set KEY=VALUE` (VALUE read as JSON when it parses), "
             "`load(MODEL, KEY=VALUE)`, or in a model's `Model.codegen_defaults`. Every option is part of the "
             "build's content hash: each configuration gets a build folder of its own "
             "(`<model>-<hash8>`), so switching back and forth does not rebuild. An unknown option, or a "
             "value of the wrong type, is refused before anything is generated.", "",
             "| option | type | default | meaning | read by |", "| --- | --- | --- | --- | --- |"]
    for option in codegen_options():
        meaning = option.meaning.replace("|", "\\|")
        lines.append(f"| `{option.name}` | {option.type_name} | `{_default(option)}` | {meaning} | "
                     f"{', '.join(option.readers)} |")
    return "\n".join(lines) + "\n"


def families_text(width: int = 100) -> str:
    """``symkf families``: each family a model can list in ``Model.filters``, with x0/P0/Q meanings."""
    lines = ["filter families (Model.filters = (...)); a filter is made by CompiledModel.filter(name, x0, P0, Q)", ""]
    for family, guide in FAMILY_GUIDE.items():
        lines.append(f"{family}  (filters: {guide.filters})")
        for label, text in (("", guide.summary), ("x0: ", guide.x0), ("P0: ", guide.P0), ("Q:  ", guide.Q),
                            ("cost: ", guide.cost)):
            lines += textwrap.wrap(label + text, width, initial_indent="    ", subsequent_indent="        ")
    return "\n".join(lines)


def families_markdown() -> str:
    """The family table of the documentation's filter guide."""
    lines = ["| family | filters | x0 | P0 | Q | cost per step |", "| --- | --- | --- | --- | --- | --- |"]
    for family, g in FAMILY_GUIDE.items():
        lines.append(f"| `{family}` | {g.filters} | {g.x0} | {g.P0} | {g.Q} | {g.cost} |")
    return "\n".join(lines) + "\n"


"""The input contract every filter enforces before it writes a buffer.

One function per kind of argument; each returns a clean float64 value or raises ``ValueError``
naming the argument and what was wrong. Nothing here touches a filter's state.

- real scalars: a number (not a string, bool or array), finite; ``dt`` > 0;
- time: the ``t`` of a call is the filter's clock (within a few roundings, :func:`on_clock`): a
  jump or a step backwards is an error, never a silent gap;
- arrays: numbers of exactly the declared shape (a bool inside a list or tuple is refused, not read as 0 or 1);
- covariances: P and Q symmetric positive semi-definite, R symmetric positive definite, finite;
- masks: exactly 0 or 1 everywhere;
- innovation gates: a probability in (0, 1) or a threshold > 0, not both;
- runs: times 1-D, finite, strictly increasing; step lengths 1-D, finite, > 0, the first may be 0
  (a run that starts with the update at the filter's time);
- NaN policy: ``nan="raise"`` (default: a NaN/Inf measurement is an error) or ``nan="mask"``
  (that component is skipped);
- dictionaries (R per measurement, options): unknown keys are errors.
"""
from __future__ import annotations

import math
import numbers

import numpy as np

#: Relative tolerance of the symmetry and semi-definiteness checks of a covariance.
SYMMETRY_RTOL = 1e-9
PSD_RTOL = 1e-9
NAN_POLICIES = ("raise", "mask")


def real(name: str, value) -> float:
    """``value`` as a float: a real number (a 0-d numeric array is accepted), never a string."""
    if type(value) is float:
        result = value
    elif isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_)):
        result = float(value)
    elif isinstance(value, np.ndarray) and value.shape == () and value.dtype.kind in "fiu":
        result = float(value)
    else:
        raise ValueError(f"{name}: expected a real number, got {type(value).__name__} {value!r:.40}")
    if not math.isfinite(result):
        raise ValueError(f"{name}: must be finite, got {result}")
    return result


#: A call's t agrees with the filter's clock within CLOCK_DT_RTOL x dt plus CLOCK_ULPS roundings
#: of the larger time: a caller's t0 + k dt and the clock's (t0 + (k-1) dt) + dt differ by a few
#: roundings, a jump by much more. The C fast path (_fastcall.c on_clock) uses the same numbers.
CLOCK_DT_RTOL = 1e-6
CLOCK_ULPS = 16.0


def is_on_clock(t: float, clock: float, dt: float = 0.0) -> bool:
    """Whether time ``t`` is the clock's time (within the roundings above)."""
    scale = max(1.0, abs(t), abs(clock))
    return abs(t - clock) <= CLOCK_DT_RTOL * dt + CLOCK_ULPS * np.finfo(float).eps * scale


def on_clock(value, clock: float, dt: float = 0.0, call: str = "step") -> float:
    """The time ``value`` of a ``call`` if it is the filter's time ``clock``; ValueError naming both
    times and how to move the clock on purpose otherwise."""
    t = real("t", value)
    if is_on_clock(t, clock, dt):
        return t
    if t > clock:
        how = (f"to propagate over the gap, call predict({clock!r}, {t - clock!r}) first (or step with "
               f"dt = {t - clock!r}); to restart the clock at {t!r} without propagating, set filter.t = {t!r}")
    else:
        how = (f"a filter does not step backwards; to restart at {t!r}, set filter.t = {t!r} "
               "(and x, P for that time)")
    side = "ahead of" if t > clock else "behind"
    raise ValueError(f"t: {call} at t = {t!r}, but the filter's time is {clock!r} ({abs(t - clock):.6g} s {side} it); "
                     f"{how} (t=None means the filter's time)")


def time_step(value, allow_zero: bool = False) -> float:
    """A step length: finite and > 0 (or >= 0 when ``allow_zero``, e.g. a run's first step)."""
    dt = real("dt", value)
    if dt < 0 or (dt == 0 and not allow_zero):
        raise ValueError(f"dt: must be > 0, got {dt}")
    return dt


def as_array(name: str, value, shape: tuple[int, ...], kinds: str = "fiu") -> np.ndarray:
    """``value`` as a float array of exactly ``shape``; ValueError names the argument otherwise.
    Only real numbers are accepted (numpy kinds ``kinds``): no strings, complex, objects or None."""
    try:
        raw = np.asarray(value)
    except (TypeError, ValueError):
        raw = None
    if raw is not None and isinstance(value, (list, tuple)) and _holds_bool(value):
        raise ValueError(f"{name}: expected real numbers of shape {shape}, got a bool inside {type(value).__name__}")
    if raw is None or raw.dtype.kind not in kinds:
        kind = type(value).__name__ if raw is None or raw.dtype.kind == "O" else f"{type(value).__name__} of {raw.dtype}"
        raise ValueError(f"{name}: expected real numbers of shape {shape}, got {kind}")
    array = raw.astype(float)
    if array.shape != shape:
        raise ValueError(f"{name}: expected shape {shape}, got {array.shape}")
    return array


def _holds_bool(value: list | tuple) -> bool:
    """Whether a (nested) list or tuple holds a bool, which numpy would silently read as 0 or 1."""
    return any(isinstance(item, (bool, np.bool_)) or (isinstance(item, (list, tuple)) and _holds_bool(item))
               for item in value)


def exact_array(name: str, value, shape: tuple[int, ...]) -> np.ndarray:
    """:func:`as_array` with a fast path for a float64 ndarray of the right shape (hot path)."""
    if type(value) is np.ndarray and value.dtype == np.float64 and value.shape == shape:
        return value
    return as_array(name, value, shape)


def finite_array(name: str, value, shape: tuple[int, ...]) -> np.ndarray:
    array = as_array(name, value, shape)
    if not np.isfinite(array).all():
        raise ValueError(f"{name}: contains NaN or Inf")
    return array


#: A state's quaternion must have | |q| - 1 | <= this (as the manifold kernels check, SYMKF_ERR_DOMAIN).
QUATERNION_NORM_TOLERANCE = 1e-6


def unit_quaternions(name: str, x: np.ndarray, quaternions: list[dict]) -> np.ndarray:
    """``x`` unchanged if every declared quaternion state (manifest ``quaternions``) has unit norm."""
    for qs in quaternions:
        norm = float(np.linalg.norm(x[qs["states"]]))
        if abs(norm - 1) > QUATERNION_NORM_TOLERANCE:
            raise ValueError(f"{name}: quaternion state '{qs['name']}' (entries {qs['states']}) has norm {norm:.9g}, "
                             f"expected 1 within {QUATERNION_NORM_TOLERANCE:g} (normalise it)")
    return x


def covariance(name: str, value, n: int, definite: bool = False) -> np.ndarray:
    """An n x n covariance: finite, symmetric and positive semi-definite (definite if asked)."""
    matrix = finite_array(name, value, (n, n))
    scale = max(float(np.max(np.abs(matrix))), np.finfo(float).tiny)
    if np.max(np.abs(matrix - matrix.T)) > SYMMETRY_RTOL * scale:
        raise ValueError(f"{name}: not symmetric")
    if definite:
        try:
            np.linalg.cholesky(matrix)
        except np.linalg.LinAlgError:
            raise ValueError(f"{name}: not positive definite") from None
    elif np.any(np.diag(matrix) < 0) or np.linalg.eigvalsh(matrix)[0] < -PSD_RTOL * scale:
        raise ValueError(f"{name}: not positive semi-definite")
    return matrix


def mask(value, shape: tuple[int, ...]) -> np.ndarray:
    """An availability mask: exactly 0 or 1 everywhere."""
    array = as_array("mask", value, shape, kinds="fiub")
    if not np.isin(array, (0.0, 1.0)).all():
        raise ValueError(f"mask: entries must be exactly 0 or 1, got {np.unique(array).tolist()}")
    return array


#: The innovation gate of a measurement the user set none for: a consistent filter refuses about
#: one update in 10^9 (chi2(1) threshold 37.3, 6.1 sigma; chi2(3) 44.6), a gross outlier (a
#: 1e30 m range) is refused with status SYMKF_GATED. ``gate={name: None}`` turns it off.
DEFAULT_GATE_PROBABILITY = 1.0 - 1e-9


def gate(probability, threshold, size: int) -> np.ndarray:
    """A chi-square innovation gate's thresholds per number of used components 1..size: the
    ``probability`` quantile of chi2(k), or ``threshold`` for every k; neither: zeros (no gate)."""
    gate = np.zeros(size)
    if probability is not None and threshold is not None:
        raise ValueError("gate: give a probability or a threshold, not both")
    if probability is not None:
        probability = real("probability", probability)
        if not 0 < probability < 1:
            raise ValueError(f"probability: must be in (0, 1), got {probability}")
        from scipy.stats import chi2       # here, not at import: scipy.stats takes ~0.5 CPU-s to import
        gate = chi2.ppf(probability, np.arange(1, gate.size + 1))
    elif threshold is not None:
        threshold = real("threshold", threshold)
        if threshold <= 0:
            raise ValueError(f"threshold: must be > 0, got {threshold}")
        gate[:] = threshold
    return gate


def nan_policy(value) -> str:
    if value not in NAN_POLICIES:
        raise ValueError(f"nan: expected one of {NAN_POLICIES}, got {value!r}")
    return value


def run_times(times) -> np.ndarray:
    """Run times: 1-D, finite, strictly increasing."""
    array = np.asarray(times) if not isinstance(times, (str, bytes)) else None
    if array is None or array.dtype.kind not in "fiu":
        raise ValueError(f"times: expected real numbers, got {type(times).__name__}")
    array = array.astype(float)
    if array.ndim != 1:
        raise ValueError(f"times: expected a 1-D array, got shape {array.shape}")
    if not np.isfinite(array).all():
        raise ValueError("times: contains NaN or Inf")
    if np.any(np.diff(array) <= 0):
        raise ValueError("times: must be strictly increasing")
    return array


def run_steps(dt) -> np.ndarray:
    """A run's step lengths: 1-D, finite, > 0 except the first, which may be 0."""
    array = as_array("dt", dt, np.shape(dt))
    if array.ndim != 1:
        raise ValueError(f"dt: expected a 1-D array, got shape {array.shape}")
    if not (np.isfinite(array).all() and np.all(array[1:] > 0) and np.all(array[:1] >= 0)):
        raise ValueError("dt: every step must be finite and > 0 (the first may be 0)")
    return array


def known_keys(name: str, given: dict | None, known) -> dict:
    """``given`` (or {}) with every key in ``known``; ValueError names the unknown ones."""
    given = {} if given is None else given
    if not isinstance(given, dict):
        raise ValueError(f"{name}: expected a dict keyed by {sorted(known)}, got {type(given).__name__}")
    unknown = sorted(set(given) - set(known))
    if unknown:
        raise ValueError(f"{name}: unknown key(s) {unknown}; expected some of {sorted(known)}")
    return given


def read_only(array: np.ndarray) -> np.ndarray:
    """A read-only view of a buffer the C code writes (users inspect it, never assign into it). Its
    base is a read-only memoryview, so numpy refuses to make it writeable again: x and P change
    only through the filter's calls, which its trusted steps rely on (runtime/fastpath.py)."""
    return np.asarray(memoryview(array).toreadonly())

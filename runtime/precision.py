"""Float that works or says why: after a run of a single-precision build, each carried state's
float spacing is compared with the filter's own standard deviation of that state.

A float number x has a spacing of 2^(e - 23) (about 6e-8 |x|): a geocentric radius of 6.4e6 m is
carried to 0.5 m. When that spacing is not small against the state's 1-sigma, every prediction
x + f dt is rounded by a sizeable fraction of the uncertainty the filter claims, the rounding is
systematic (an increment below half the spacing is lost), and no covariance form can repair it:
the square-root filters keep P positive definite, not x resolved (measured: the launcher without
its declared offsets, r RMS 40-89 m in float against 0.5-0.66 m in double, every filter;
scenarios/toolchain/square_root_float.py). What helps: an offset (``Model.state(..., offset=)``,
e.g. the Earth's radius, so the carried number is an altitude), or a double build. A scale that is
a power of two changes nothing (the relative spacing of float is the same at every magnitude).

A float build already says at build time what it will not resolve for the states whose range
the model declares (models/float_range.py, codegen/float_check.py); this check needs no declaration.

:func:`check` returns the findings; :func:`warn_unresolved` issues one
:class:`FloatResolutionWarning` naming the states, the numbers and the remedy.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

# the warning and its threshold are the build check's too (codegen/float_check.py)
from symkf.codegen.float_check import SPACING_FRACTION, FloatResolutionWarning


@dataclass(frozen=True)
class Finding:
    state: str
    step: int               # the step of the worst ratio
    magnitude: float        # |carried value| there (kernel units)
    spacing: float          # float spacing there, in the state's unit
    sigma: float            # the filter's 1-sigma there, in the state's unit

    def __str__(self) -> str:
        return (f"state '{self.state}': carried as {self.magnitude:.4g}, float spacing {self.spacing:.3g} against a "
                f"1-sigma of {self.sigma:.3g} (ratio {self.spacing / self.sigma:.2g}, step {self.step})")


def sigmas(P: np.ndarray, factor: bool) -> np.ndarray:
    """Standard deviations per step from covariances (N, n, n), or from lower factors (rows' norms)."""
    P = np.asarray(P, dtype=float)
    if factor:
        return np.sqrt(np.einsum("kij,kij->ki", np.tril(P), np.tril(P)))
    return np.sqrt(np.maximum(np.einsum("kii->ki", P), 0.0))


def check(names, x_kernel: np.ndarray, sigma_kernel: np.ndarray, scale: np.ndarray | None = None) -> list[Finding]:
    """Findings for states whose float spacing at the carried value exceeds SPACING_FRACTION of the
    1-sigma at some step. ``x_kernel``, ``sigma_kernel``: (N, n) in the kernel's (possibly scaled)
    units; ``scale``: the build's per-state scale (the findings are given in the state's unit)."""
    x = np.abs(np.asarray(x_kernel, dtype=np.float32))
    spacing = np.spacing(x).astype(float)
    ratio = spacing / np.maximum(sigma_kernel, np.finfo(float).tiny)
    scale = np.ones(x.shape[1]) if scale is None else np.asarray(scale, dtype=float)
    found = []
    for i, name in enumerate(names):
        k = int(np.argmax(ratio[:, i]))
        if ratio[k, i] > SPACING_FRACTION:
            found.append(Finding(name, k, float(x[k, i]), spacing[k, i] * scale[i], float(sigma_kernel[k, i]) * scale[i]))
    return found


def warn_unresolved(filt, x_kernel: np.ndarray, P_kernel: np.ndarray) -> list[Finding]:
    """After a run of a float build: warn (FloatResolutionWarning) if a state is unresolved."""
    if filt._dtype != np.float32 or P_kernel is None:
        return []
    names = [s["name"] for s in filt.model["states"]]
    if len(names) != x_kernel.shape[1] or P_kernel.shape[1] != len(names):
        return []                                  # a manifold filter's error state: not compared here
    scaling = filt._scaling
    found = check(names, x_kernel, sigmas(P_kernel, filt._form is not None), None if scaling is None else scaling.scale)
    if found:
        warnings.warn(f"filter '{filt.family}' of a float build: the float state cannot resolve "
                      + "; ".join(map(str, found))
                      + ". Rounding of x + f dt is then a sizeable, systematic fraction of the uncertainty "
                      "(no covariance form repairs that). What helps: an offset on the state "
                      "(Model.state(..., offset=...)) so that the carried number is small, or a double build; "
                      "a power-of-two scale= changes nothing.", FloatResolutionWarning, stacklevel=4)
    return found

"""What a model may say about the numbers its states take, so that a single-precision build can
tell at build time whether float resolves them (codegen/float_check.py).

A float number v has a spacing of about 6e-8 |v| (2^-23 relative): a state whose typical value is
large against the uncertainty a filter should resolve cannot be carried in float, whatever the
covariance form (runtime/precision.py measures it after a run). The build cannot know a state's
values or its filters' uncertainty from the equations; a model says them with :func:`declare_range`:

    from symkf.models.float_range import declare_range
    r = m.state("r", "m", "geocentric radius")
    declare_range(m, "r", low=6.378e6, high=6.7e6, sigma=0.3)    # r in [6378, 6700] km, known to 0.3 m

``low``, ``high``: the values the state takes in use (state units); ``sigma``: the smallest
1-sigma a filter of it should resolve (state units). A state without a declaration is not checked
at build (the run's check still applies).
"""
from __future__ import annotations

import numpy as np

from .base import Model
from .errors import ModelError


def declare_range(model: Model, name: str, low: float, high: float, sigma: float) -> None:
    """Declare the values [low, high] and the smallest 1-sigma of state ``name`` (module docstring)."""
    if name not in model.state_names():
        raise ModelError(f"model '{model.name}': declare_range: no state '{name}'; states: {model.state_names()}")
    try:
        low, high, sigma = float(low), float(high), float(sigma)
    except (TypeError, ValueError):
        raise ModelError(f"model '{model.name}': declare_range('{name}'): low, high and sigma must be numbers") from None
    if not (np.isfinite(low) and np.isfinite(high) and low <= high and np.isfinite(sigma) and sigma > 0):
        raise ModelError(f"model '{model.name}': declare_range('{name}'): low <= high, both finite, and sigma finite "
                         f"and > 0, got low={low}, high={high}, sigma={sigma}")
    model.state_ranges[name] = (low, high, sigma)

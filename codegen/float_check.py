"""Float at build: a single-precision build says, before any run, which declared states it will
not resolve (runtime/precision.py gives the measured reason, after a run).

For each state with a declared range (models/float_range.py: values in [low, high], smallest
1-sigma sigma), the largest carried number is max |v| over the range, or max |v - offset| / scale
in a scaled build (codegen/scaling.py); its float spacing, back in the state's unit, is compared
with sigma. A spacing above
``SPACING_FRACTION`` sigma (the run check's threshold) is a :class:`FloatResolutionWarning` naming
the state, the numbers and what would help: an offset inside the range (``Model.state(..., offset=...)``,
with the build's scaling on) or a double build. A state without a declared range is not checked
here: nothing in the equations says what values it takes or how well a filter knows it.
"""
from __future__ import annotations

import warnings

import numpy as np

from symkf.models.base import Model
from .spec import CodegenConfig

#: A state whose float spacing exceeds this fraction of its 1-sigma is reported, here and by the
#: after-run check (runtime/precision.py). Measured (one run, 20 Hz small error): with the
#: launcher's declared offsets the largest ratio is 0.37 (V) and float is within 1.3x of double;
#: without them r reaches 1.5 and theta 3.8, and float is 80x off.
SPACING_FRACTION = 1.0


class FloatResolutionWarning(UserWarning):
    """A single-precision filter cannot resolve a state at the size of its own uncertainty."""


def unresolved(model: Model, config: CodegenConfig) -> list[str]:
    """The declared states a float build of ``config`` cannot resolve, each as a sentence; [] for a
    double build or a model without declared ranges."""
    if config.precision != "float":
        return []
    found = []
    for i, name in enumerate(model.state_names()):
        if name not in model.state_ranges:
            continue
        low, high, sigma = model.state_ranges[name]
        scale, offset = (model.state_scale[i], model.state_offset[i]) if config.scaled else (1.0, 0.0)
        carried = max(abs(low - offset), abs(high - offset)) / scale
        spacing = float(np.spacing(np.float32(carried))) * scale
        if spacing > SPACING_FRACTION * sigma:
            found.append(f"state '{name}': carried as {carried:.4g}, float spacing {spacing:.3g} against a declared "
                         f"1-sigma of {sigma:.3g} (ratio {spacing / sigma:.2g})")
    return found


def warn_at_build(model: Model, config: CodegenConfig) -> list[str]:
    """Warn (FloatResolutionWarning) if a float build will not resolve a declared state."""
    found = unresolved(model, config)
    if found:
        warnings.warn(f"model '{model.name}', float build: the float state will not resolve " + "; ".join(found)
                      + ". What helps: an offset inside the state's range (Model.state(..., offset=...)) with the "
                      "build's scaling on, so that the carried number is small, or a double build.",
                      FloatResolutionWarning, stacklevel=3)
    return found

"""What a :class:`~symkf.runtime.filters.Filter` is, in words: its ``repr`` (model, family, time,
the states with their units, what P is the covariance of) and its ``chart``.

A manifold filter's P is not the covariance of x: each quaternion's four components are one
3-vector rotation error in the family's chart (``codegen/families/chart.py``), so a P0 copied
from a paper in another chart is off by a factor. The repr says which, beside the numbers.
"""
from __future__ import annotations

import numpy as np

#: The quaternion error of each manifold chart (codegen option ``manifold_chart``).
CHART_MEANING = {
    "rotation_vector": "rotation vector dtheta [rad] (q = q_hat * Exp(dtheta))",
    "vector_part": "vector part dp of the error quaternion [half-angle: |dp| = sin(angle/2)] (paper 000 eq 34)",
}


def config_value(filt, key: str, default=None):
    """A codegen option of the build behind ``filt`` (its manifest, or the VM backend's config)."""
    backend = filt._backend
    manifest = getattr(backend, "manifest", None)
    if manifest is not None:
        extra = dict(tuple(item) for item in manifest.get("config", {}).get("extra", []))
    else:
        extra = dict(getattr(backend, "config_extra", ()))
    return extra.get(key, default)


def chart_of(filt) -> str:
    """What ``filt.P`` (and Q) are the covariance of."""
    if "P" not in filt._buffers:
        return "none (this filter carries no covariance)"
    quaternions, n = filt.model.get("quaternions", []), filt._buffers["P"].shape[0]
    if n == filt.n:                      # a plain family (also one opted in on a quaternion state)
        return f"the state x itself ({filt.n} x {filt.n}, in the states' units)"
    chart = config_value(filt, "manifold_chart", "rotation_vector")
    names = ", ".join(q["name"] for q in quaternions)
    return (f"the error state ({n} x {n}): each quaternion ({names}) as a 3-vector {CHART_MEANING.get(chart, chart)}, "
            "the other states in their units")


def describe(filt) -> str:
    """The filter's repr: model, family, time, states (name = value [unit]) and P's chart."""
    x = np.asarray(filt.x)
    rows = [f"  {s['name']} = {x[i]:.6g} [{s.get('unit', '-')}]" for i, s in enumerate(filt.model["states"])]
    measurements = list(filt.spec.measurements)
    lines = [f"<symkf Filter '{filt.family}' of model '{filt.model['name']}' at t = {filt.t!r}; "
             f"measurements {measurements}; P: {chart_of(filt)}>", *rows]
    return "\n".join(lines)

"""Estimated parameters (models/estimation.py) at the filter's boundary: the initial state,
covariance and process noise of the augmented state from a user's x0, P0, Q of the model's own
states and the declaration (initial value, sigma, random walk), and the estimate and its sigma
by name."""
from __future__ import annotations

import numpy as np


def declared(compiled) -> list[dict]:
    """The estimated parameters of a compiled model (state and Q indices, initial, sigma, random_walk)."""
    return list(compiled.model.get("estimated_parameters", []))


def augment(compiled, x0, P0, Q) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """x0, P0 (of the model's own states) and Q (of its states, or of its noises) extended by each
    estimated parameter: its initial value, sigma^2 and random-walk intensity; cross terms 0."""
    params = declared(compiled)
    k = len(params)
    x0, P0, Q = np.asarray(x0, float), np.asarray(P0, float), np.asarray(Q, float)
    x = np.r_[x0, [p["initial"] for p in params]]
    P = np.zeros((x0.size + k, x0.size + k))
    P[:x0.size, :x0.size] = P0
    Qa = np.zeros((Q.shape[0] + k, Q.shape[0] + k))
    Qa[:Q.shape[0], :Q.shape[0]] = Q
    for p in params:
        P[p["state"], p["state"]] = p["sigma"] ** 2
        Qa[p["q_index"], p["q_index"]] = p["random_walk"]
    return x, P, Qa


def report(filt) -> dict[str, tuple[float, float]]:
    """{parameter: (estimate, sigma)} of a filter of a model with estimated parameters."""
    x, P = filt.x, filt.P
    return {p["name"]: (float(x[p["state"]]), float(np.sqrt(P[p["state"], p["state"]])))
            for p in filt.model.get("estimated_parameters", [])}

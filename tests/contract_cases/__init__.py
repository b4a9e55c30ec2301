"""The filters the contract test holds to one contract: one module per model, each giving its
cases (``cases()``), a short valid input record (``inputs(case, k)`` for step k >= 1, starting at
the case's ``t0``) and its NumPy reference over that record (``reference_states(case, n)``).

A new model or filter family joins the contract with one module here (and its name in
:data:`MODULES`); tests/test_contract.py has no branch per model: what differs between filters
is said by a case's fields (``tags``, ``runs_by_steps``, ``mask_size``, ``tolerance``).
"""
from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from symkf.runtime import Filter

#: One module per model, in the order the cases are listed.
MODULES = ("launcher", "geo_satellite", "attitude", "marg", "spinner", "leo")


@dataclass
class Case:
    """One filter of one model, with the module that knows its inputs and its NumPy reference.

    Attributes:
        tags: what the contract's feature tests select by: "separate_update" (predict and update
            kernels, a vector z an outlier can be added to), "quaternion_z" (z is a unit
            quaternion), "gradient_descent" (no covariance; a sample is a direction).
        runs_by_steps: a run is given step lengths (run_steps: every step has dt > 0).
        mask_size: the mask's length (1: the whole measurement is used or not; 0: z's length).
        tolerance: the largest error against the NumPy reference, in the filter's own sigma.
    """

    model: str
    name: str
    x0: np.ndarray
    P0: np.ndarray | None = None
    Q: np.ndarray | None = None
    measurement: str = ""
    options: dict = field(default_factory=dict)
    module: object = None
    t0: float = 0.0
    tags: frozenset = frozenset()
    runs_by_steps: bool = False
    mask_size: int = 0
    tolerance: float = 1e-8

    @property
    def id(self) -> str:
        return f"{Path(self.model).stem}-{self.name}-{self.measurement}"

    def make(self, compiled, P_scale: float = 1.0):
        P0 = None if self.P0 is None else self.P0 * P_scale
        return Filter(compiled, self.name, self.x0, P0, self.Q, t0=self.t0, **self.options)

    def inputs(self, k: int) -> dict:
        return self.module.inputs(self, k)

    def reference_states(self, n: int) -> list[np.ndarray]:
        return self.module.reference_states(self, n)

    def mask_length(self) -> int:
        return self.mask_size or int(np.size(self.inputs(1)["z"]))


def all_cases() -> list[Case]:
    cases = []
    for name in MODULES:
        module = importlib.import_module(f"{__name__}.{name}")
        for case in module.cases():
            case.module = module
            cases.append(case)
    return cases

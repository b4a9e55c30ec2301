"""The state and settings of a :class:`~symkf.runtime.filters.Filter`, as it shows them: x, P,
Q, p, R per measurement, the innovation gates, the last update's diagnostics y and S, its repr
and P's chart. Every setter checks its value by :mod:`symkf.runtime.contract` (and, for a float
build, that float holds it) before anything is written; a scaled build converts at this boundary.
"""
from __future__ import annotations

from collections.abc import Mapping
from types import MappingProxyType

import numpy as np

from . import calls, contract
from .buffers import fits
from .contract import covariance, read_only
from .description import chart_of, describe


class FilterState:
    """x, P, Q, p, R, gates and diagnostics of a filter (the buffers and fast path are the
    :class:`~symkf.runtime.filters.Filter`'s)."""

    def __repr__(self) -> str:
        return describe(self)

    @property
    def chart(self) -> str:
        """What P (and Q) are the covariance of: the state itself, or the error state of a manifold
        filter with each quaternion's rotation error in this family's chart."""
        return chart_of(self)

    @property
    def x(self) -> np.ndarray:
        """The state estimate (a read-only view of the buffer the C code writes; a read-only
        physical copy for a scaled build)."""
        if self._scaling is None:
            return self._views["x"]
        return read_only(self._scaling.x_from_kernel(self._buffers["x"]))

    @x.setter
    def x(self, value) -> None:
        x = contract.finite_array("x", value, self._buffers["x"].shape)
        x = contract.unit_quaternions("x", x, self.model.get("quaternions", []))
        self._write_state("x", x if self._scaling is None else self._scaling.x_to_kernel(x))

    @property
    def P(self) -> np.ndarray:
        """The covariance (read-only view, or physical copy for a scaled build or a square-root
        filter); set it with a symmetric PSD matrix."""
        if self._scaling is None and self._form is None:
            return self._views["P"]
        P = self._buffers["P"] if self._form is None else self._form.from_kernel(self._buffers["P"])
        return read_only(P if self._scaling is None else self._scaling.P_from_kernel(P))

    @P.setter
    def P(self, value) -> None:
        P = covariance("P", value, self._buffers["P"].shape[0])
        P = P if self._scaling is None else self._scaling.P_to_kernel(P)
        self._write_state("P", P if self._form is None else self._form.to_kernel(P))

    @property
    def factor(self) -> np.ndarray:
        """The lower factor L, P = L L^T, a square-root filter carries (of P~ if scaled)."""
        if self._form is None:
            raise ValueError(f"factor: filter '{self.family}' carries P itself, not a factor")
        return self._views["P"]

    @property
    def Q(self) -> np.ndarray:
        Q = self._buffers["Q"]
        return read_only(Q if not self._scales_Q else self._scaling.P_from_kernel(Q))

    @Q.setter
    def Q(self, value) -> None:
        Q = covariance("Q", value, self._buffers["Q"].shape[0])
        self._write_state("Q", Q if not self._scales_Q else self._scaling.P_to_kernel(Q))

    @property
    def _scales_Q(self) -> bool:
        return self._scaling is not None and self._scaling.scales_Q

    def _write_state(self, name: str, value: np.ndarray) -> None:
        """Write a checked value; for a float build refuse one that float cannot hold (buffer unchanged)."""
        value = fits(self._dtype, name, value, " after scaling" if self._scaling is not None else "")
        self._fast.before_write()
        self._buffers[name][:] = value

    @property
    def p(self) -> np.ndarray:
        return read_only(self._buffers["p"])

    @p.setter
    def p(self, value) -> None:
        value = fits(self._dtype, "p", contract.finite_array("p", value, self._buffers["p"].shape))
        self._fast.before_write()
        self._buffers["p"][:] = value

    @property
    def R(self) -> Mapping[str, np.ndarray]:
        """Measurement noise covariances by measurement name (read-only views); set one with
        :meth:`set_R`, or several at once with ``filter.R = {name: matrix}`` (all checked first)."""
        return MappingProxyType({name: read_only(b["R"]) for name, b in self.measurements.items() if "R" in b})

    @R.setter
    def R(self, values: dict) -> None:
        values = contract.known_keys("R", values, [n for n, b in self.measurements.items() if "R" in b])
        checked = {name: self._checked_R(name, value) for name, value in values.items()}
        self._fast.before_write()
        for name, value in checked.items():
            self.measurements[name]["R"][:] = value

    def _checked_R(self, measurement: str, value) -> np.ndarray:
        buffers = self._measurement(measurement)
        name = f"R[{measurement}]"
        return fits(self._dtype, name, covariance(name, value, buffers["R"].shape[0], definite=True))

    def set_R(self, measurement: str, value) -> None:
        """Measurement noise covariance of ``measurement`` (symmetric positive definite)."""
        value = self._checked_R(measurement, value)
        self._fast.before_write()
        self.measurements[measurement]["R"][:] = value

    def set_gate(self, measurement: str, probability: float | None = None, threshold: float | None = None) -> None:
        """Chi-square innovation gate: an update whose y^T S^-1 y exceeds the ``probability``
        quantile of chi2(k) (k = used components), or ``threshold``, is skipped (state unchanged,
        status SYMKF_GATED). Neither given: no gate (a filter's default gate is
        :data:`~symkf.runtime.contract.DEFAULT_GATE_PROBABILITY`, see :class:`~symkf.runtime.filters.Filter`)."""
        buffers = self._measurement(measurement)
        if "gate" not in buffers:
            raise ValueError(f"gate: filter '{self.family}' has no innovation gate")
        gate = contract.gate(probability, threshold, buffers["gate"].size)
        self._fast.before_write()
        buffers["gate"][:] = gate
        self._default_gates.discard(measurement)

    def y(self, measurement: str | None = None) -> np.ndarray:
        """Innovation of the last update with ``measurement``."""
        return self._diagnostic("y", measurement)

    def S(self, measurement: str | None = None) -> np.ndarray:
        """Innovation covariance of the last update with ``measurement``."""
        return self._diagnostic("S", measurement)

    def _diagnostic(self, key: str, measurement: str | None) -> np.ndarray:
        name = calls.measurement_name(self, measurement, "step")
        return self._fast.diagnostic(key, name)

    def _measurement(self, name: str | None) -> dict[str, np.ndarray]:
        name = calls.measurement_name(self, name, "step") if name is None else name
        if name not in self.measurements:
            raise ValueError(f"measurement: '{name}' is not one of {list(self.measurements)}")
        return self.measurements[name]


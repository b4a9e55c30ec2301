"""Paper 004's qualitative claims (section 5, Table 3), checked state by state on eq (11).

- the UKF is at least as accurate as the EKF: per case, every state's whole-flight RMS (eq (11));
- the EKF/UKF gap grows with the initial error (large eq (10) vs small eq (9)), and at the slower
  radar (10 Hz vs 20 Hz): the median over the six states of the EKF/UKF whole-flight RMS ratio,
  larger by more than ``GAP_MARGIN``;
- ours, not the paper's: fixed-interval RTS smoothing never raises a cell's whole-flight RMS.
"""
from __future__ import annotations

import numpy as np

from symkf.models import launcher as L
from symkf.scenarios.claims import Claim
from .campaign import FILTERS, STATE_NAMES, CaseResult

UNITS = dict(zip(STATE_NAMES, L.TABLE3_UNITS))
#: A gap counts as larger when the median EKF/UKF ratio grows by more than this factor.
GAP_MARGIN = 1.05


def ratio(result: CaseResult) -> np.ndarray:
    """EKF / UKF whole-flight RMS per state."""
    return result.whole_flight("ekf") / np.maximum(result.whole_flight("ukf"), 1e-300)


def claims(results: list[CaseResult]) -> list[Claim]:
    """Every claim the cases run allow (a gap claim needs both of its cases)."""
    by_label = {r.case.label: r for r in results}
    out = [_ukf_le_ekf(r) for r in results]
    for rate in sorted({r.case.rate_hz for r in results}, reverse=True):
        pair = by_label.get(f"{rate}Hz small"), by_label.get(f"{rate}Hz large")
        if all(pair):
            out.append(_gap(f"gap_larger_for_large_error_{rate}Hz", f"at {rate} Hz the EKF/UKF gap is larger after "
                            "the large initial error (eq (10)) than after the small one (eq (9))", *pair))
    for init in ("small", "large"):
        pair = by_label.get(f"20Hz {init}"), by_label.get(f"10Hz {init}")
        if all(pair):
            out.append(_gap(f"gap_larger_at_10Hz_{init}", f"with the {init} initial error the EKF/UKF gap is larger "
                            "with radar at 10 Hz than at 20 Hz", *pair))
    out.append(_smoother(results))
    return out


def _ukf_le_ekf(result: CaseResult) -> Claim:
    ekf, ukf = result.whole_flight("ekf"), result.whole_flight("ukf")
    worse = [f"{s} {u:.3g} vs {e:.3g} {UNITS[s]}" for s, e, u in zip(STATE_NAMES, ekf, ukf) if u > e]
    compared = (f"whole-flight RMS (eq (11)) of the 6 states, {result.case.label}: "
                + (f"UKF above EKF in {', '.join(worse)} (UKF vs EKF)" if worse else
                   "UKF at or below EKF in all six (" + ", ".join(f"{s} {u:.3g} vs {e:.3g}" for s, e, u in
                                                                  zip(STATE_NAMES, ekf, ukf)) + ")"))
    label = result.case.label.replace(" ", "_")
    return Claim(f"ukf_le_ekf_every_state_{label}", "the UKF is at least as accurate as the EKF in every state",
                 compared, not worse)


def _gap(name: str, says: str, reference: CaseResult, other: CaseResult) -> Claim:
    """The median EKF/UKF ratio of ``other`` above ``GAP_MARGIN`` x that of ``reference``."""
    low, high = float(np.median(ratio(reference))), float(np.median(ratio(other)))
    compared = (f"median over the 6 states of EKF/UKF whole-flight RMS: {other.case.label} {high:.3f} vs "
                f"{reference.case.label} {low:.3f} (larger means above {GAP_MARGIN:g} x {low:.3f} = {GAP_MARGIN * low:.3f})")
    return Claim(name, says, compared, high > GAP_MARGIN * low)


def smoother_exceptions(results: list[CaseResult]) -> list[str]:
    """The cells (case, state, filter) whose smoothed whole-flight RMS exceeds the filter's."""
    return [f"{r.case.label} {state} {family.upper()}" for r in results for family in FILTERS
            for state, smoothed, filtered in zip(STATE_NAMES, r.whole_flight(f"{family}_rts"), r.whole_flight(family))
            if smoothed > filtered]


def _smoother(results: list[CaseResult]) -> Claim:
    above = smoother_exceptions(results)
    cells = len(results) * len(FILTERS) * len(STATE_NAMES)
    compared = (f"whole-flight RMS of each filter vs its RTS smoothing, {cells} cells: "
                + (f"smoothed above filtered in {len(above)}: {', '.join(above)}" if above else "smoothed at or below in all"))
    return Claim("rts_le_filter_every_cell", "(ours, not the paper's) fixed-interval RTS smoothing never raises "
                 "the whole-flight RMS error", compared, not above)

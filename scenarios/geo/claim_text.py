"""Paper 003's claims (Table 7, section 4) in plain language, and the numbers each was checked on.

``compare.claims_case1`` ... ``claims_case4`` decide each claim from the runs (``value``) and keep
its evidence; here each gets what the paper says and a one-line account of the cells compared,
with the numbers, for summary.json and the printout (:class:`symkf.scenarios.claims.Claim`).
"""
from __future__ import annotations

import numpy as np

from symkf.scenarios.claims import Claim

#: What the paper says, per claim.
SAYS = {
    "one_failed_gyro_is_tolerated": "with any one of the four gyros failed (no EKF) the attitude loop still converges",
    "some_failed_pairs_diverge": "with some pairs of gyros failed (no EKF) the attitude loop diverges",
    "some_failed_pairs_converge": "with some pairs of gyros failed (no EKF) the attitude loop still converges",
    "gyros_A_and_C_failed_cannot_be_controlled": "with gyros A and C failed and no EKF the satellite cannot be controlled",
    "integral_compensates_gyro_bias": "the PID's integral term compensates the gyro bias (no EKF)",
    "gyro_B_failed_with_bias_still_converges": "with gyro B failed and biased gyros (no EKF) the loop still converges",
    "ekf_converges_in_the_2hz_loop": "the continuous-discrete EKF in the 2 Hz loop converges, with and without bias and noise",
    "gyro_bias_estimated": "the EKF estimates the gyro biases",
    "noise_barely_changes_attitude": "sensor noise barely changes the attitude with the EKF in the loop",
    "integral_as_without_bias_once_bias_estimated": "once the bias is estimated, the integrated angle is as without bias",
    "ekf_in_the_loop_matches_no_ekf_loop": "the loop with the EKF gives the same attitude as the loop without it",
    "controlled_with_gyros_AC_failed": "with the EKF the satellite is controlled with gyros A and C failed",
    "controlled_with_gyros_ABCD_failed": "with the EKF the satellite is controlled with all four gyros failed",
    "all_failed_matches_no_failure": "with the EKF and all gyros failed the attitude is as with no failure",
    "rts_rms_at_most_filter_rms": "(ours, not the paper's) the CD-EKF RTS smoother's whole-run RMS estimation "
                                  "error is at or below the filter's in every block",
}


def _number(value) -> str:
    if isinstance(value, (bool, np.bool_)) or value is None:
        return str(value)
    if isinstance(value, (int, float, np.number)):
        return f"{value:.3g}"
    if isinstance(value, (list, tuple, np.ndarray)):
        return "[" + ", ".join(_number(v) for v in value) + "]"
    return str(value)


def _cells(evidence) -> str:
    """The evidence, one level of names deep, numbers to 3 digits."""
    if not isinstance(evidence, dict):
        return _number(evidence)
    parts = []
    for key, value in evidence.items():
        if isinstance(value, dict):       # one level deep: a nested entry by its name only
            inner = ", ".join(k.replace('_', ' ') if isinstance(v, dict) else f"{k.replace('_', ' ')} {_number(v)}"
                              for k, v in value.items())
            parts.append(f"{key}: {inner or 'none'}")
        else:
            parts.append(f"{key.replace('_', ' ')} {_number(value)}")
    return "; ".join(parts)


def claim(name: str, verdict: dict) -> Claim:
    """The plain-language form of one checked claim ``{"value": bool, "evidence": ..., "note": ...}``."""
    compared = _cells(verdict.get("evidence"))
    if verdict.get("note"):
        compared += f" ({verdict['note']})"
    return Claim(name, SAYS.get(name, name.replace("_", " ")), compared, bool(verdict["value"]))

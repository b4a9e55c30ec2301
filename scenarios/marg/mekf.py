"""The generated MARG multiplicative EKF (``models/marg_mekf.py``) over a recording.

Availability masks, decided per sample by rules that need nothing after the sample (so the same
rules run online):

- **heading**: used when | |m|/m₀ - 1 | <= ``MAG_NORM_TOLERANCE`` and the dip angle between m and
  the measured up direction a/|a| is within ``DIP_TOLERANCE`` of dip₀ (m₀, dip₀: medians over
  the first ``REFERENCE_SECONDS`` of the recording). Even the undisturbed BROAD trials change
  |m| by up to 7 % with the orientation, and the heading they give then disagrees with the
  optical reference: a tight 3 % keeps those samples out (mean total RMSE over trials 01, 07,
  28: 2.46 deg at 3 %, 2.45-2.54 for 2.5-3.5 % and dip 8-15 deg, 2.85 at 8 %; heading sigma 0.4).
- **gyro at rest** (the bias measurement of the model): the causal rest rule of
  :func:`at_rest` (VQF's rest detection). BROAD's gyro bias is constant within a trial (start and
  end rest phases agree to 0.01 deg/s), but the filter's estimate wandered by up to 0.17 deg/s
  during motion without it; with it the mean total RMSE went from 2.90 to 2.66 deg (same masks
  otherwise), trial 01 from 2.07 to 1.50.
- **accelerometer direction**: always used. Masking it when | |a| - g | is large was tried and
  *hurt* on BROAD (mean 3.5-3.7 deg with |a| within 10-40 % of g, vs 2.66 without: the tilt then
  rests on the gyro and the heading, and trial 28's magnet reaches it through the heading), and
  so did a chi-square gate on the whole measurement (3.10 at p = 0.9999, before the rest
  measurement). The accelerometer's own sigma (0.3) absorbs the accelerations instead.

The filter is initialised from the first sample (gravity and field directions, TRIAD) with zero
bias. One parameter set (these constants and the model's sigmas) for every trial, tuned on the
three BROAD trials it is reported on (see the README's MARG section for neighbouring sets).
"""
from __future__ import annotations

import numpy as np
from scipy.ndimage import maximum_filter1d, minimum_filter1d
from scipy.spatial.transform import Rotation

from symkf.models import marg_mekf
from symkf.runtime.runs import RunResult

MAG_NORM_TOLERANCE = 0.03
DIP_TOLERANCE = np.radians(10.0)
REFERENCE_SECONDS = 1.0
#: Rest (after VQF's rest detection, Laidig & Seel 2023, as a causal window): over the last
#: ``REST_SECONDS`` every gyro sample has |ω| <= ``REST_GYRO`` and every accelerometer axis stays
#: within ``REST_ACC`` of its window minimum; then the gyro measures its bias.
REST_SECONDS = 1.5
REST_GYRO = np.radians(2.0)
REST_ACC = 0.5
INITIAL_SIGMA = np.array([0.1, 0.1, 0.2, 0.01, 0.01, 0.01])   # rad (tilt, tilt, heading), rad/s (bias)


def initial_orientation(acc: np.ndarray, mag: np.ndarray) -> np.ndarray:
    """TRIAD: the sensor -> ENU quaternion (scalar-last) from one accelerometer and magnetometer sample."""
    up = acc / np.linalg.norm(acc)
    east = np.cross(mag, up)
    east /= np.linalg.norm(east)
    north = np.cross(up, east)
    return Rotation.from_matrix(np.vstack([east, north, up])).as_quat()


def dip_angles(acc: np.ndarray, mag: np.ndarray, mag_norm: np.ndarray | None = None) -> np.ndarray:
    """Angle (rad) of the field below the horizontal plane, per sample, using a/|a| as up
    (``mag_norm``: |m| per sample when the caller has it)."""
    up = acc / np.linalg.norm(acc, axis=1, keepdims=True)
    m = mag / (np.linalg.norm(mag, axis=1) if mag_norm is None else mag_norm)[:, None]
    return np.arcsin(np.clip(-np.sum(up * m, axis=1), -1, 1))


def _trailing(values: np.ndarray, samples: int, reduce) -> np.ndarray:
    """Per sample, the max (``reduce`` np.maximum) or min (np.minimum) over the trailing window of
    ``samples`` (the sample itself and the ones before it; shorter at the start): needs nothing
    later. A running filter (scipy.ndimage, O(N)): the window ends at the sample (origin
    (samples - 1) // 2), and the "nearest" padding before the start repeats the first sample,
    which the shorter window holds anyway, so the result is exactly the short window's."""
    running = {np.maximum: maximum_filter1d, np.minimum: minimum_filter1d}[reduce]
    return running(values, size=samples, axis=0, origin=(samples - 1) // 2, mode="nearest")


def _window_any(flags: np.ndarray, samples: int) -> np.ndarray:
    """Per sample, whether any of ``flags`` in its trailing window of ``samples`` is set (counts
    from one cumulative sum: O(N), the same booleans as a running max of the flags)."""
    count = np.cumsum(flags, dtype=np.int64)
    count[samples:] -= count[:-samples].copy()
    return count > 0


def at_rest(recording) -> np.ndarray:
    """(N,) bool: the sensor is at rest by the rule of :data:`REST_SECONDS` (False for the first window)."""
    samples = max(1, int(round(REST_SECONDS / np.median(np.diff(recording.time)))))
    spinning = _window_any(np.linalg.norm(recording.gyro, axis=1) > REST_GYRO, samples)
    acc = np.ascontiguousarray(recording.acc.T)           # one contiguous row per axis: faster windows
    spread = _trailing(acc.T, samples, np.maximum) - _trailing(acc.T, samples, np.minimum)
    rest = ~spinning & (spread <= REST_ACC).all(axis=1)
    rest[:samples - 1] = False
    return rest


def masks(recording, mag_tolerance: float = MAG_NORM_TOLERANCE, dip_tolerance: float = DIP_TOLERANCE) -> np.ndarray:
    """(N, 7) availability masks of [acc direction (3); heading; gyro at rest (3)] by the rules of
    the module docstring."""
    mag_norm = np.linalg.norm(recording.mag, axis=1)
    first = recording.time - recording.time[0] <= REFERENCE_SECONDS
    dip = dip_angles(recording.acc, recording.mag, mag_norm)
    m0, dip0 = np.median(mag_norm[first]), np.median(dip[first])
    out = np.ones((len(recording), 7))
    out[:, 3] = (np.abs(mag_norm / m0 - 1) <= mag_tolerance) & (np.abs(dip - dip0) <= dip_tolerance)
    out[:, 4:] = at_rest(recording)[:, None]
    return out


def measurements(recording) -> np.ndarray:
    """(N, 7) z of the ``marg`` measurement: a/|a|, the heading 0 and the gyro sample."""
    acc = recording.acc / np.linalg.norm(recording.acc, axis=1, keepdims=True)
    return np.column_stack([acc, np.zeros(len(recording)), recording.gyro])


def make_filter(compiled, recording, gate: float | None = None):
    """The MEKF initialised from the recording's first sample."""
    x0 = np.r_[initial_orientation(recording.acc[0], recording.mag[0]), np.zeros(3)]
    options = {"gate": {"marg": gate if gate else None}}     # no gate unless asked (the tables' setting)
    return compiled.filter("mekf", x0, np.diag(INITIAL_SIGMA**2), marg_mekf.process_noise_psd(),
                           t0=float(recording.time[0]), **options)


def run_recording(compiled, recording, gate: float | None = None) -> RunResult:
    """Filter a whole recording in one compiled run (the online filter: every rule causal);
    ``result.q`` is sensor -> ENU. Its fixed-interval smoothing: ``mekf_offline.py``."""
    filt = make_filter(compiled, recording, gate)
    return filt.run(recording.time, measurements(recording), "marg", q=recording.mag, mask=masks(recording),
                    u=recording.gyro)

"""The offline pass of the MARG MEKF (``models/marg_mekf.py``): the error-state RTS smoother over a
forward run whose inputs may use later samples, as a smoother may (``mekf_rts`` of ``symkf
compare marg``). Three choices differ from the online filter of ``mekf.py``, decided by what
the BROAD dev trials 01, 07, 28 showed (mean total RMSE of the smoothing 2.72 deg with the online
run's inputs and model):

- **Two-sided magnetometer decision.** The online heading rule (``mekf.masks``) tests each
  sample's |m| and dip against tolerances; |m| is noisy (±5 % at rest), so inside a stretch of
  disturbed field (trial 01's motion: |m| 7 % high, the field's heading 2.8 deg off the rest
  value against the optical reference) single samples pass by noise. The forward filter hides
  it (its gyro drift, +0.1 deg/s there, happens to cancel it); the smoother's backward
  information does not (a time-reversed run of the same filter: heading RMSE 6.3 deg on trial
  01 vs 0.6 forward), and the smoothing lands between the two (3.5 deg). Offline, a sample's
  heading is used only when the online rule accepts it *and* at least half of the samples within
  ±``HEADING_VOTE_SECONDS``/2 of it are accepted too (a majority vote over a centred window:
  an isolated pass inside a disturbed stretch is dropped). Smoothing 2.72 -> 2.28 deg.
- **The gyro half a sample later.** The run predicts over (t_{k-1}, t_k] with the rate u_k;
  online it is the gyro sample k. Reading the gyro at k, k + 0.5, k + 1 (interpolated) gave
  online mean total RMSE 2.46 / 2.42 / 2.52 deg (trial 07, fast rotation: 2.07 / 1.92 / 2.20),
  and k - 1 gave 2.96: BROAD's gyro lags its accelerometer and magnetometer by about a sample.
  Offline, u_k = (g_k + g_{k+1}) / 2 (the last sample held); with the vote above, 2.28 -> 2.13.
- **Gyro scale factors.** The model with the gyro's scale-factor errors as states
  (``models/marg_mekf.py``, ``build(gyro_scale=True)``: ``marg_mekf_scale``, prior 1-sigma
  ``SCALE_PRIOR_SIGMA``). Gyro-only heading drifts 0.1 deg/s through trial 01's motion (its
  rest bias holds to 0.01 deg/s), and trials 01 and 28 turn one way for about two minutes (net 360 and
  -2520 deg of heading); the smoother fits k to the whole trial: 2.13 -> 1.64 deg (prior
  0.1 %: 1.69). Online the states do not pay (forward mean 3.1 deg with them, 2.46 without):
  a filter cannot know k before the motion that reveals it.

Everything else (masks of the accelerometer and the gyro at rest, sigmas, initialisation) is the
online filter's: one parameter set.
"""
from __future__ import annotations

import numpy as np
from scipy.ndimage import uniform_filter1d

from symkf.models import marg_mekf
from symkf.runtime import load
from symkf.runtime.smoothing import SmoothedRun
from . import mekf

#: Width (s) of the centred window of the heading vote.
HEADING_VOTE_SECONDS = 0.25
#: Column of the heading in ``mekf.masks``.
HEADING = 3


def voted_heading(accepted: np.ndarray, samples: int) -> np.ndarray:
    """(N,) bool: ``accepted`` and at least half of the centred window of ``samples`` accepted
    (the window shortened at the ends by repeating the end samples)."""
    accepted = np.asarray(accepted, dtype=float)
    share = uniform_filter1d(accepted, size=max(1, samples), mode="nearest")
    return (accepted > 0.5) & (share >= 0.5 - 1e-12)


def masks(recording) -> np.ndarray:
    """``mekf.masks`` with the heading decided two-sided (the module docstring)."""
    out = mekf.masks(recording)
    samples = int(round(HEADING_VOTE_SECONDS / np.median(np.diff(recording.time))))
    out[:, HEADING] = voted_heading(out[:, HEADING], samples)
    return out


def gyro_rates(recording) -> np.ndarray:
    """(N, 3) u_k = (g_k + g_{k+1}) / 2, the last sample held: the gyro half a sample later."""
    g = recording.gyro
    return np.vstack([0.5 * (g[:-1] + g[1:]), g[-1:]])


def load_model():
    """The compiled ``marg_mekf_scale`` (built on first use)."""
    return load(marg_mekf.build(gyro_scale=True))


def make_filter(compiled, recording):
    """The MEKF of ``marg_mekf_scale`` initialised as the online one (``mekf.make_filter``), k = 0."""
    x0 = np.r_[mekf.initial_orientation(recording.acc[0], recording.mag[0]), np.zeros(6)]
    P0 = np.diag(np.r_[mekf.INITIAL_SIGMA, [marg_mekf.SCALE_PRIOR_SIGMA] * 3] ** 2)
    return compiled.filter("mekf", x0, P0, marg_mekf.process_noise_psd(gyro_scale=True),
                           t0=float(recording.time[0]), gate={"marg": None})


def smooth_recording(compiled, recording) -> SmoothedRun:
    """The offline forward run of ``compiled`` (:func:`load_model`) and its error-state RTS
    smoothing (``x_smooth[:, :4]`` sensor -> ENU, ``x_smooth[:, 7:]`` the scale-factor errors)."""
    filt = make_filter(compiled, recording)
    return filt.run(recording.time, mekf.measurements(recording), "marg", q=recording.mag, mask=masks(recording),
                    u=gyro_rates(recording), smooth=True)

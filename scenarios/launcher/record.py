"""A recorded radar pass of the launcher, written for flight code outside Python.

``python -m symkf.scenarios.launcher.record --out radar.txt`` flies the KSLV-I truth past the
tracking radars (the campaign's "correct" preset: WGS-84 stations, small initial error), draws
one noisy radar record and writes it as plain text that ``examples/flight/main.c`` reads with
``scanf``: the filter's initial state, covariance and tuning, then one line per radar sample with
exactly the (t, dt) the compiled ``run`` uses (step k predicts from t[k] to t[k] + dt[k] and
updates with z[k]; the first step has dt = 0).
"""
from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from symkf.models import launcher as L
from .campaign import PRESETS, Case, case_flight, initial_estimate, measurements

FORMAT = "symkf-radar-record-1"


@dataclass
class RadarRecord:
    """One filter run's inputs: initial estimate, tuning and the per-step radar samples."""

    measurement: str
    times: np.ndarray          # (N,) sample times
    x0: np.ndarray
    P0: np.ndarray
    Q: np.ndarray
    R: np.ndarray
    q: np.ndarray              # (N, nq) station parameters per sample
    z: np.ndarray              # (N, nz)
    mask: np.ndarray           # (N, nz)

    @property
    def t(self) -> np.ndarray:
        """Start of each step (the first step has dt = 0), as the compiled run uses it."""
        return np.concatenate([self.times[:1], self.times[:-1]])

    @property
    def dt(self) -> np.ndarray:
        return np.diff(self.times, prepend=self.times[:1])


def radar_record(rate_hz: int = 20, duration: float = L.T_INSERTION, seed: int = 0,
                 initial_error: str = "small", preset: str = "correct") -> RadarRecord:
    """The radar record of Monte Carlo run 0 of one campaign case (same draws as the campaign)."""
    tuning = PRESETS[preset]["tuning"]
    measurement = L.RADAR_MEASUREMENTS[tuning["stations"]]
    case = Case(rate_hz, initial_error)
    times, truth, track = case_flight(rate_hz, duration, measurement)
    z = measurements(seed, case, 0, track)
    x0, P0 = initial_estimate(case, truth[0], tuning["P0_floor"])
    sigma = np.asarray(L.build().measurements[measurement].sigma)
    return RadarRecord(measurement, times, x0, P0, tuning["Q"] * tuning["ekf_q_scale"], np.diag(sigma**2),
                       np.asarray(track.station_params(), dtype=float), z, np.ones_like(z))


def write_radar_record(path: str | Path, record: RadarRecord) -> Path:
    """Plain text, every number with 17 significant digits (exact in double), matrices column-major."""
    def line(values) -> str:
        return " ".join(f"{v:.17g}" for v in np.ravel(values, order="F"))
    n, nx = record.times.size, record.x0.size
    nz, nq = record.z.shape[1], record.q.shape[1]
    lines = [f"{FORMAT} launcher {record.measurement}", f"{n} {nx} {nz} {nq}",
             line(record.x0), line(record.P0), line(record.Q), line(record.R)]
    lines += [line(np.concatenate([[t], [dt], q, z, m]))
              for t, dt, q, z, m in zip(record.t, record.dt, record.q, record.z, record.mask)]
    path = Path(path)
    path.write_text("\n".join(lines) + "\n")
    return path


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description="write a launcher radar record for examples/flight/main.c")
    parser.add_argument("--out", default="radar_record.txt")
    parser.add_argument("--rate", type=int, default=20, choices=L.RADAR_RATES_HZ)
    parser.add_argument("--duration", type=float, default=L.T_INSERTION, help="seconds of flight (default: to insertion)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--initial-error", default="small", choices=("small", "large"))
    args = parser.parse_args(argv)
    record = radar_record(args.rate, args.duration, args.seed, args.initial_error)
    path = write_radar_record(args.out, record)
    print(f"wrote {path}: {record.times.size} samples of '{record.measurement}' at {args.rate} Hz")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

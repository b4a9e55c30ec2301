"""Recordings for the MARG experiment (paper 001): BROAD trials and the x-io Fusion example CSV.

- :func:`load_recording`: BROAD ``.mat`` or ``.hdf5`` trials (Laidig et al. 2021, CC BY 4.0; optical reference)
  and the x-io Fusion CSV (MIT; no reference), as :class:`Recording`.
- :func:`run_recording`: a gradient-descent filter (``scenarios/marg/filter.py``) over a whole recording.

Quaternions are scalar-last ``[x, y, z, w]`` everywhere in the project; BROAD's scalar-first
``opt_quat`` is converted on loading.
"""
from __future__ import annotations

import csv
import functools
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from symkf.runtime.runs import RunResult
from symkf.scenarios.marg.filter import initial_orientation, samples


#: Where a user gets the recordings (said by every error and test skip that needs one).
WHERE_BROAD = ("BROAD trials (Laidig et al. 2021, CC BY 4.0): download from https://github.com/dlaidig/broad "
               "and pass --data (or set $SYMKF_DATA_DIR to a folder holding broad/)")
WHERE_XIO = ("x-io Fusion example recording (MIT): sensor_data.csv of https://github.com/xioTechnologies/Fusion, "
             "saved as fusion_sensor_data.csv in $SYMKF_DATA_DIR")


def data_dir() -> Path:
    """``$SYMKF_DATA_DIR``, else ``../shared/data`` beside a source checkout, else ``./data``."""
    env = os.environ.get("SYMKF_DATA_DIR")
    if env:
        return Path(env)
    beside_checkout = Path(__file__).resolve().parents[3] / "shared" / "data"
    return beside_checkout if beside_checkout.is_dir() else Path("data")


# ---------------------------------------------------------------------- recordings
@dataclass
class Recording:
    """One recording, arrays per sample; ``reference``/``movement`` are None without ground truth.

    Attributes:
        time: (N,) s.  dt: (N,) s, ``dt[k] = time[k] - time[k-1]``, ``dt[0] = 0``.
        gyro: (N, 3) rad/s.  acc: (N, 3) (any unit; only its direction is used).
        mag: (N, 3) (any unit).  reference: (N, 4) scalar-last, sensor -> ENU, NaN where missing.
        movement: (N,) bool, the benchmark's movement phases.
    """

    name: str
    time: np.ndarray
    gyro: np.ndarray
    acc: np.ndarray
    mag: np.ndarray
    reference: np.ndarray | None = None
    movement: np.ndarray | None = None
    source: str = ""

    @functools.cached_property
    def dt(self) -> np.ndarray:
        """Sample intervals, computed once (read per sample by the benches' loops)."""
        return np.diff(self.time, prepend=self.time[:1])

    def __len__(self) -> int:
        return self.time.size

    def head(self, n: int) -> "Recording":
        """The first ``n`` samples (for quick tests)."""
        cut = slice(0, n)
        return Recording(self.name, self.time[cut], self.gyro[cut], self.acc[cut], self.mag[cut],
                         None if self.reference is None else self.reference[cut],
                         None if self.movement is None else self.movement[cut], self.source)


def load_broad(path: str | Path) -> Recording:
    """A BROAD trial, as MATLAB v5 ``.mat`` (scipy) or BROAD's own ``.hdf5`` (h5py; the form of the
    full 39-trial download): 285.714 Hz IMU, optical reference quaternion (ENU, scalar-first)."""
    path = Path(path)
    data = _read_hdf5(path) if path.suffix in HDF5_SUFFIXES else _read_mat(path)
    rate = float(np.squeeze(data["sampling_rate"]))
    n = data["imu_gyr"].shape[0]
    opt = np.asarray(data["opt_quat"], dtype=float)
    return Recording(path.stem, np.arange(n) / rate, np.asarray(data["imu_gyr"], float),
                     np.asarray(data["imu_acc"], float), np.asarray(data["imu_mag"], float),
                     opt[:, [1, 2, 3, 0]], np.asarray(data["movement"]).ravel() == 1,
                     "BROAD (Laidig et al. 2021, doi:10.3390/data6070072), CC BY 4.0")


HDF5_SUFFIXES = (".hdf5", ".h5")
BROAD_FIELDS = ("imu_gyr", "imu_acc", "imu_mag", "opt_quat", "movement")


def _read_mat(path: Path) -> dict:
    from scipy.io import loadmat
    return loadmat(path)


def _read_hdf5(path: Path) -> dict:
    """BROAD's HDF5 layout: one dataset per field, ``sampling_rate`` as a file attribute."""
    try:
        import h5py
    except ImportError:
        raise ValueError(f"{path}: reading BROAD .hdf5 files needs h5py (pip install 'symkf[broad]')") from None
    try:
        handle = h5py.File(path, "r")
    except OSError as exc:
        raise ValueError(f"{path}: not a readable HDF5 file ({exc})") from None
    with handle:
        missing = [f for f in BROAD_FIELDS if f not in handle]
        if missing:
            raise ValueError(f"{path}: not a BROAD trial (no datasets {missing})")
        data = {name: np.asarray(handle[name]) for name in BROAD_FIELDS}
        data["sampling_rate"] = handle.attrs["sampling_rate"] if "sampling_rate" in handle.attrs \
            else np.asarray(handle["sampling_rate"])
    return data


def broad_trials(folder: str | Path) -> list[Path]:
    """The BROAD trials in ``folder``, one file per trial (``.hdf5`` preferred over ``.mat``), by name."""
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder}: no such folder")
    by_trial: dict[str, Path] = {}
    for path in sorted(folder.iterdir()):
        if path.suffix in HDF5_SUFFIXES + (".mat",) and path.stem[:2].isdigit():
            if path.stem not in by_trial or path.suffix in HDF5_SUFFIXES:
                by_trial[path.stem] = path
    if not by_trial:
        raise FileNotFoundError(f"{folder}: no BROAD trials (NN_name.hdf5 or .mat)")
    return [by_trial[k] for k in sorted(by_trial)]


def load_xio_csv(path: str | Path) -> Recording:
    """The x-io Fusion example CSV: time (s), gyro (deg/s), accelerometer (g), magnetometer (µT)."""
    path = Path(path)
    with open(path, newline="") as handle:
        reader = csv.reader(handle)
        header = next(reader)
        rows = np.array([[float(v) for v in row] for row in reader if row])
    if rows.ndim != 2 or rows.shape[1] != 10:
        raise ValueError(f"{path}: expected 10 columns (time, gyro xyz, acc xyz, mag xyz), got header {header}")
    return Recording(path.stem, rows[:, 0], np.deg2rad(rows[:, 1:4]), rows[:, 4:7], rows[:, 7:10],
                     source="x-io Technologies Fusion example data, MIT")


def load_recording(path: str | Path) -> Recording:
    """A BROAD ``.mat`` / ``.hdf5`` or an x-io ``.csv`` by file suffix."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such recording")
    if path.suffix in (".mat",) + HDF5_SUFFIXES:
        return load_broad(path)
    if path.suffix == ".csv":
        return load_xio_csv(path)
    raise ValueError(f"{path}: expected a BROAD .mat / .hdf5 or an x-io .csv file")


def run_recording(compiled, filt, recording: Recording, measurement: str = "marg", initialize: bool = True) -> RunResult:
    """Initialise ``filt`` (a gradient-descent Filter of ``compiled``, ``scenarios/marg/filter.py``)
    from the first sample and its clock at the recording's start (if asked), and filter the whole
    recording."""
    z = samples(recording.acc, recording.mag, measurement)
    if initialize:
        filt.x = initial_orientation(compiled, z[0], measurement)
        filt.t = float(recording.time[0])
    return filt.run(recording.time, z, measurement, u=recording.gyro)

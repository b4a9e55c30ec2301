"""The saved results of a comparison: one self-describing series file per output folder.

Every ``symkf compare`` writes its time series (RMS(t), NEES(t), error and sigma histories) and
its per-run or per-trial rows to ``series.nc``: netCDF-4 through xarray, each variable with its
dimension names, ``units`` and ``long_name`` attributes, the comparison's name and configuration
as global attributes. ``xarray.open_dataset(folder / "series.nc")`` reads it with any netCDF tool.

xarray and its netCDF engine (h5netcdf, over the h5py the tests already use) are the optional
extra ``results`` (``pip install 'symkf[results]'``). Without them the same variables go to
``series.npz`` (plain NumPy, a JSON ``__meta__`` entry holding the dimensions and attributes) and
stderr says once how to get netCDF. Either file loads back as a :class:`Series`, from which
``symkf plot <folder>`` redraws the comparison's figures without running a filter.

A variable whose length differs between cases (a 10 Hz and a 20 Hz time axis) is stored padded
with NaN on a common dimension, with the true lengths beside it (:func:`padded`, :func:`trimmed`).
"""
from __future__ import annotations

import json
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

NETCDF_FILE = "series.nc"
NPZ_FILE = "series.npz"
HOW_TO_GET_NETCDF = "pip install 'symkf[results]' (xarray + h5netcdf + h5py)"
_said_fallback = False


@dataclass
class Variable:
    """One array with its dimension names and attributes (``units``, ``long_name``, ...)."""

    dims: tuple[str, ...]
    data: np.ndarray
    attrs: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.dims, self.data = tuple(self.dims), np.asarray(self.data)
        if self.data.ndim != len(self.dims):
            raise ValueError(f"{self.data.ndim}-d data with dimensions {self.dims}")


@dataclass
class Series:
    """What a comparison saves: ``comparison`` (its ``symkf compare`` name), variables by name
    (those named after their only dimension are its coordinates) and global attributes."""

    comparison: str
    variables: dict[str, Variable]
    attrs: dict = field(default_factory=dict)

    def __getitem__(self, name: str) -> np.ndarray:
        return self.variables[name].data

    def labels(self, name: str) -> list[str]:
        """A coordinate of labels as Python strings."""
        return [str(v) for v in self.variables[name].data]


def var(dims, data, units: str | None = None, long_name: str | None = None, **attrs) -> Variable:
    """A :class:`Variable` with the usual attributes (``units`` "1" for a pure number)."""
    named = {k: v for k, v in (("units", units), ("long_name", long_name)) if v is not None}
    return Variable(tuple(dims), np.asarray(data), {**named, **attrs})


def padded(arrays: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Arrays of one rank, stacked on a new first axis and NaN-padded along their first axis;
    and their lengths (to give back to :func:`trimmed`)."""
    lengths = np.array([len(a) for a in arrays])
    out = np.full((len(arrays), lengths.max(initial=0), *np.shape(arrays[0])[1:]), np.nan)
    for i, a in enumerate(arrays):
        out[i, :len(a)] = a
    return out, lengths


def trimmed(data: np.ndarray, length: int) -> np.ndarray:
    """One padded entry cut back to its length (the inverse of :func:`padded`)."""
    return np.asarray(data)[:int(length)]


def netcdf_available() -> bool:
    """xarray, h5netcdf and its h5py importable (the ``results`` extra; h5netcdf installs without
    h5py, and then cannot write)."""
    try:
        import h5netcdf  # noqa: F401
        import h5py  # noqa: F401
        import xarray  # noqa: F401
    except ImportError:
        return False
    return True


def save(series: Series, folder: Path) -> Path:
    """Write ``folder/series.nc`` (or ``series.npz`` without the ``results`` extra, said once on
    stderr); a stale file of the other kind is removed so that ``symkf plot`` reads this one."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    attrs = {"comparison": series.comparison, **series.attrs}
    if netcdf_available():
        path = _save_netcdf(series, attrs, folder / NETCDF_FILE)
        (folder / NPZ_FILE).unlink(missing_ok=True)
        return path
    global _said_fallback
    if not _said_fallback:
        print(f"symkf: wrote {NPZ_FILE} (NumPy); for a self-describing netCDF {NETCDF_FILE}: {HOW_TO_GET_NETCDF}",
              file=sys.stderr)
        _said_fallback = True
    meta = {"attrs": attrs, "variables": {k: {"dims": v.dims, "attrs": v.attrs} for k, v in series.variables.items()}}
    path = folder / NPZ_FILE
    np.savez_compressed(path, __meta__=np.array(json.dumps(meta, default=_plain)), **{k: v.data for k, v in series.variables.items()})
    (folder / NETCDF_FILE).unlink(missing_ok=True)
    return path


def _save_netcdf(series: Series, attrs: dict, path: Path) -> Path:
    import xarray as xr
    coords = {k: (v.dims, v.data, v.attrs) for k, v in series.variables.items() if v.dims == (k,)}
    data = {k: (v.dims, v.data, v.attrs) for k, v in series.variables.items() if k not in coords}
    dataset = xr.Dataset(data, coords=coords, attrs={k: _attr(v) for k, v in attrs.items()})
    encoding = {k: {"compression": "gzip", "compression_opts": 4} for k, v in series.variables.items()
                if v.data.dtype.kind == "f" and v.data.size > 1}
    tmp = path.with_name(f".{path.name}.tmp")
    dataset.to_netcdf(tmp, engine="h5netcdf", encoding=encoding)
    tmp.replace(path)
    return path


def _plain(value):
    """NumPy numbers and arrays in attributes (a series read back from netCDF) as JSON."""
    if isinstance(value, (np.generic, np.ndarray)):
        return value.tolist()
    raise TypeError(f"attribute of type {type(value).__name__} is not a number, string or list")


def _attr(value):
    """netCDF attributes are numbers or strings: anything else goes as JSON text."""
    return value if isinstance(value, (str, int, float, np.number)) else json.dumps(value)


def find(folder: Path) -> Path | None:
    """The series file of ``folder`` (netCDF first), or None."""
    for name in (NETCDF_FILE, NPZ_FILE):
        if (Path(folder) / name).is_file():
            return Path(folder) / name
    return None


def load(folder: Path) -> Series:
    """The :class:`Series` saved in ``folder``; FileNotFoundError names the folder and what writes it."""
    path = find(folder)
    if path is None:
        raise FileNotFoundError(f"{folder}: no saved series ({NETCDF_FILE} or {NPZ_FILE}); "
                                "`symkf compare <name> --out FOLDER` writes one")
    if path.suffix == ".npz":
        with np.load(path, allow_pickle=False) as data:
            if "__meta__" not in data:
                raise FileNotFoundError(f"{path}: written by an earlier symkf, without its dimensions and units; "
                                        "run the comparison again to write it anew")
            meta = json.loads(str(data["__meta__"]))
            variables = {k: Variable(tuple(m["dims"]), data[k], m["attrs"]) for k, m in meta["variables"].items()}
        attrs = meta["attrs"]
    else:
        if not netcdf_available():
            raise FileNotFoundError(f"{path}: reading netCDF needs {HOW_TO_GET_NETCDF}")
        variables, attrs = _load_netcdf(path)
    return Series(str(attrs.pop("comparison")), variables, attrs)


def _load_netcdf(path: Path) -> tuple[dict, dict]:
    import xarray as xr
    with xr.open_dataset(path, engine="h5netcdf") as dataset:
        variables = {}
        for name, item in dataset.variables.items():
            data = item.values
            if data.dtype.kind == "O":                   # netCDF strings come back as objects
                data = data.astype(str)
            variables[str(name)] = Variable(item.dims, data, dict(item.attrs))
        return variables, dict(dataset.attrs)


def attribute(series: Series, name: str):
    """A global attribute, JSON text decoded back (see :func:`save`)."""
    value = series.attrs[name]
    if isinstance(value, str) and value[:1] in "[{":
        return json.loads(value)
    return value.item() if isinstance(value, np.generic) else value


def folders_with_series(folder: Path) -> list[Path]:
    """``folder`` and its sub-folders (one level: e.g. results/attitude/scenario_I) that hold a series file."""
    folder = Path(folder)
    found = [folder] if find(folder) else []
    if folder.is_dir():
        found += sorted(p for p in folder.iterdir() if p.is_dir() and find(p))
    return found

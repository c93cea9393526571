"""Density time series in HDF5 (``yauyau filter --density OUT.h5``), laid out the CF way.

    /                       attrs Conventions="CF-1.10", title, model_id, model_name, method, state
    /time       (T,)        unlimited; the filter time t of each snapshot (units left to the user)
    /step       (T,)        the step number k of each snapshot
    /<var>      (G_i,)      one coordinate variable per state variable (a dimension scale), axis X/Y/Z
    /density    (T, G_1[, G_2])   the joint density p(x, t | y) on the product grid (n = 1, 2 only)
    /marginal_<var> (T, G_i)      each variable's marginal density (every n)

Every data variable has its dimensions attached as HDF5 dimension scales (what netCDF-4 readers and
xarray use), ``long_name`` and ``coordinates``.  A coordinate named like a reserved dataset gets the
prefix ``coord_``.  Storage knows files, not math: the caller hands in the numbers.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from .errors import StoreError
from .files import temporary_beside

RESERVED = {"time", "step", "density"}
AXES = "XYZ"


def coordinate_name(var: str) -> str:
    return f"coord_{var}" if var in RESERVED or var.startswith("marginal_") else var


class DensityWriter:
    """Append density snapshots to a new file; ``close()`` moves it into place atomically."""

    def __init__(self, path: str | os.PathLike, state: list[str], axes: list[np.ndarray], joint: bool,
                 attrs: dict[str, Any]):
        self.path = Path(path)
        try:
            self._tmp = temporary_beside(self.path, ".h5")  # the user's umask, not mkstemp's 0600
            self._file = h5py.File(self._tmp, "w")
        except OSError as exc:
            raise StoreError("density", f"cannot write {path}: {exc}") from None
        f = self._file
        f.attrs.update({"Conventions": "CF-1.10", "title": "yauyau conditional density",
                        "state": list(state), **{k: v for k, v in attrs.items() if v is not None}})
        self.state = list(state)
        self.count = 0
        time = f.create_dataset("time", shape=(0,), maxshape=(None,), dtype="f8", chunks=(256,))
        time.attrs.update(long_name="time", axis="T", standard_name="time")
        time.make_scale("time")
        step = f.create_dataset("step", shape=(0,), maxshape=(None,), dtype="i8", chunks=(256,))
        step.attrs.update(long_name="filter step k (t = k dt on a regular grid)")
        step.dims[0].attach_scale(time)
        step.dims[0].label = "time"
        coords = []
        for i, (var, axis) in enumerate(zip(state, axes, strict=True)):
            c = f.create_dataset(coordinate_name(var), data=np.asarray(axis, float))
            c.attrs.update(long_name=var, axis=AXES[i] if i < 3 else "")
            c.make_scale(var)
            coords.append(c)
        self._coords = coords
        names = " ".join(c.name.lstrip("/") for c in coords)
        self._joint = None
        if joint:
            shape = tuple(len(a) for a in axes)
            d = f.create_dataset("density", shape=(0, *shape), maxshape=(None, *shape), dtype="f8",
                                 chunks=(1, *shape), compression="gzip", compression_opts=4)
            d.attrs.update(long_name="conditional density p(x, t | observations)",
                           coordinates=f"time {names}")
            d.dims[0].attach_scale(time)
            d.dims[0].label = "time"
            for k, (var, c) in enumerate(zip(state, coords, strict=True)):
                d.dims[k + 1].attach_scale(c)
                d.dims[k + 1].label = var
            self._joint = d
        self._marginals = []
        for var, c in zip(state, coords, strict=True):
            m = f.create_dataset(f"marginal_{var}", shape=(0, len(c)), maxshape=(None, len(c)), dtype="f8",
                                 chunks=(16, len(c)), compression="gzip", compression_opts=4)
            m.attrs.update(long_name=f"marginal conditional density of {var}",
                           coordinates=f"time {c.name.lstrip('/')}")
            m.dims[0].attach_scale(time)
            m.dims[1].attach_scale(c)
            m.dims[0].label, m.dims[1].label = "time", var
            self._marginals.append(m)

    def append(self, step: int, t: float, marginals: list[np.ndarray],
               joint: np.ndarray | None = None) -> None:
        k = self.count
        for name, value in (("time", t), ("step", step)):
            self._file[name].resize((k + 1,))
            self._file[name][k] = value
        if self._joint is not None:
            self._joint.resize((k + 1, *self._joint.shape[1:]))
            self._joint[k] = joint
        for dataset, values in zip(self._marginals, marginals, strict=True):
            dataset.resize((k + 1, dataset.shape[1]))
            dataset[k] = values
        self.count = k + 1

    def close(self) -> None:
        self._file.close()
        os.replace(self._tmp, self.path)

    def abort(self) -> None:
        try:
            self._file.close()
        finally:
            Path(self._tmp).unlink(missing_ok=True)


@dataclass(frozen=True)
class DensitySeries:
    """A density file read back: ``axes[i]`` the grid of ``state[i]``; ``joint`` (T, G...) or None."""

    state: list[str]
    time: np.ndarray
    step: np.ndarray
    axes: list[np.ndarray]
    marginals: list[np.ndarray]
    joint: np.ndarray | None
    attrs: dict[str, Any]


def read_density(path: str | os.PathLike) -> DensitySeries:
    try:
        with h5py.File(path, "r") as f:
            if f.attrs.get("title") != "yauyau conditional density":
                raise StoreError("density", f"{path} is not a density file of yauyau filter --density")
            state = [str(s) for s in f.attrs["state"]]
            axes = [f[coordinate_name(v)][()] for v in state]
            marginals = [f[f"marginal_{v}"][()] for v in state]
            joint = f["density"][()] if "density" in f else None
            return DensitySeries(state=state, time=f["time"][()], step=f["step"][()], axes=axes,
                                 marginals=marginals, joint=joint, attrs=dict(f.attrs))
    except (OSError, KeyError) as exc:
        raise StoreError("density", f"cannot read {path}: {exc}") from None

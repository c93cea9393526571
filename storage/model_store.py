"""HDF5 model store: one file per precomputed model, named by the content hash of its spec.

    id = sha256("yauyau-model/<FORMAT_VERSION>\\n" + canonical spec JSON)[:20]   (hex)

Layout of ``<id>.h5``: root attributes ``format_version``, ``model_id``, ``spec`` (JSON),
``created`` (UTC ISO 8601), ``versions`` (JSON: numpy, scipy, h5py, scikit-fem), ``attrs``
(JSON, the caller's, plus the ``summary`` the store adds), ``meta_sha256`` (hash of all of the
above plus the name, shape, dtype and sha256 of every array); group ``arrays`` holds one dataset
per array, each with a fletcher32 checksum (per chunk, checked by HDF5 on read).  Group ``lazy``
(only when the caller has such arrays: an atlas of propagators, one row per centre) holds (K, ...)
datasets chunked one row per chunk, with the sha256 of every row in the attribute ``row_sha256``;
they are not read by ``load`` but row by row (:class:`LazyArrays`), each row checked against its
hash.

Writes go to a hidden temporary file in the same directory which is flushed, fsynced and
``os.replace``d, so a killed writer never leaves a half-written file under the final name.  The rows
of the lazy arrays may be written as they are computed (:class:`ModelWriter`: an atlas centre by
centre, never all in memory), the arrays and the hashes at the end.

A listing (``yauyau models``, ``GET /v1/models`` and ``/v1/models/{id}``) shows a model's summary:
its name, state variables, n, m, dt, radius, basis size and domain (:data:`SUMMARY_FIELDS`).  It is
computed once, when the file is written (:func:`spec_summary`), and stored in ``attrs["summary"]``;
every listing reads it from there.  A file written before summaries were stored (yauyau 0.2.0) has
none: its summary is computed from its stored spec when it is listed, by the same function.
Storage knows files, not math: it never imports solver or service.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import importlib.metadata
import json
import os
import re
import secrets
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from .errors import NotFound, StoreError

# 2 (yauyau 0.2): the filter method chosen at precompute is stored (attrs "method", "method_reason")
FORMAT_VERSION = 2
ID_LENGTH = 20
SUFFIX = ".h5"
TMP_PREFIX = ".tmp-"
_ID = re.compile(rf"^[0-9a-f]{{{ID_LENGTH}}}\Z")
_ARRAY_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]{0,63}\Z")
_TMP = re.compile(rf"^{re.escape(TMP_PREFIX)}[0-9a-f]{{{ID_LENGTH}}}-(\d+)-[0-9a-f]+{re.escape(SUFFIX)}\Z")
_LIBRARIES = ("numpy", "scipy", "h5py", "scikit-fem")
# Integer arrays (mesh cells, node indices) shrink 3-15x under shuffle+gzip at no cost.  Dense
# float arrays shrink by 5-35% but load 20-40x slower (bench/storage.py, bench/results/storage.md),
# so they are compressed only on request (ModelStore(compress_floats=True)).
_INTEGER_KINDS = "iub"


@dataclass(frozen=True)
class StoredModel:
    id: str
    spec_json: str
    arrays: dict[str, np.ndarray]
    attrs: dict[str, Any]
    lazy: "LazyArrays | None" = None  # the rows of the ``lazy`` group, read on demand


class LazyArrays:
    """The ``lazy`` group of a verified model file, read one row at a time (the file is opened per
    read; a row whose bytes do not hash to the verified ``row_sha256`` raises StoreError)."""

    def __init__(self, path: Path, rows: dict[str, tuple[tuple[int, ...], str, list[str]]]):
        self.path, self._rows = path, rows

    @property
    def names(self) -> list[str]:
        return sorted(self._rows)

    def shape(self, name: str) -> tuple[int, ...]:
        return self._rows[name][0]

    def read(self, name: str, k: int) -> np.ndarray:
        """Row k of the lazy array ``name``."""
        if name not in self._rows:
            raise StoreError(f"lazy.{name}", f"no such lazy array in {self.path.name}")
        shape, dtype, hashes = self._rows[name]
        if not 0 <= int(k) < shape[0]:
            raise StoreError(f"lazy.{name}", f"row {k} is out of range (0..{shape[0] - 1})")
        try:
            with h5py.File(self.path, "r") as h5:
                row = np.ascontiguousarray(h5["lazy"][name][int(k)])
        except (OSError, KeyError, ValueError, TypeError, RuntimeError) as exc:
            raise StoreError("model", f"model file {self.path.name}: cannot read row {k} of {name}: "
                                      f"{_short(exc)}") from None
        if row.dtype.str != dtype or row.shape != shape[1:] or \
                hashlib.sha256(row.tobytes()).hexdigest() != hashes[int(k)]:
            raise StoreError("model", f"model file {self.path.name}: row {k} of {name} does not match its "
                                      "checksum (file altered or replaced since it was opened)")
        return row


SUMMARY_FIELDS = ("name", "state", "n", "m", "dt", "radius", "basis", "follow", "region", "shape")


@dataclass(frozen=True)
class ModelSummary:
    """What ``list()`` reports, read from attributes only (the stored summary, :data:`SUMMARY_FIELDS`,
    and the method chosen at precompute); ``error`` is set for an unreadable file."""

    id: str
    name: str | None = None
    state: list[str] | None = None
    n: int | None = None
    m: int | None = None
    dt: float | None = None
    radius: float | None = None
    basis: int | None = None
    follow: bool | None = None  # [domain] follow: the ball re-centres on the posterior
    region: list[list[float]] | None = None  # [domain] region: where a following ball may go (an atlas)
    shape: list[list[float]] | str | None = None  # [domain] shape: the ellipsoid's covariance, or "posterior"
    created: str | None = None
    file_size: int = 0
    error: str | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {"id": self.id, "name": self.name, "state": self.state, "n": self.n, "m": self.m,
                "dt": self.dt,
                "radius": self.radius, "basis": self.basis, "follow": self.follow, "region": self.region,
                "shape": self.shape, "created": self.created,
                "file_size": self.file_size, "error": self.error, **self.extra}


def canonical_spec(spec_json: str) -> str:
    """Sorted, compact JSON of a spec document (idempotent on ModelSpec.canonical_json())."""
    try:
        doc = json.loads(spec_json)
    except (TypeError, ValueError) as exc:
        raise StoreError("spec_json", f"not valid JSON: {exc}") from None
    if not isinstance(doc, dict):
        raise StoreError("spec_json", "must be a JSON object")
    return json.dumps(doc, sort_keys=True, separators=(",", ":"))


def model_id(spec_json: str) -> str:
    """Content hash of the canonical spec JSON and the format version."""
    text = f"yauyau-model/{FORMAT_VERSION}\n{canonical_spec(spec_json)}"
    return hashlib.sha256(text.encode("utf-8")).hexdigest()[:ID_LENGTH]


def library_versions() -> dict[str, str | None]:
    out: dict[str, str | None] = {}
    for name in _LIBRARIES:
        try:
            out[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            out[name] = None
    return out


def _meta_digest(spec: str, attrs: str, created: str, versions: str, layout: list) -> str:
    doc = json.dumps([FORMAT_VERSION, spec, attrs, created, versions, layout], separators=(",", ":"))
    return hashlib.sha256(doc.encode("utf-8")).hexdigest()


def _layout(arrays: dict[str, np.ndarray]) -> list:
    # The content hash of every array catches what fletcher32 cannot: a damaged chunk index
    # makes HDF5 return the fill value (zeros) for a chunk without any checksum being read.
    return [[name, list(arr.shape), arr.dtype.str, hashlib.sha256(arr.tobytes()).hexdigest()]
            for name, arr in sorted(arrays.items())]


def _lazy_layout(rows: dict[str, tuple[tuple[int, ...], str, list[str]]]) -> list:
    return [[f"lazy/{name}", list(shape), dtype, hashes]
            for name, (shape, dtype, hashes) in sorted(rows.items())]


def _checked_arrays(arrays: dict[str, Any]) -> dict[str, np.ndarray]:
    if not isinstance(arrays, dict):
        raise StoreError("arrays", "must be a mapping of names to arrays")
    out = {}
    for name, value in arrays.items():
        if not isinstance(name, str) or not _ARRAY_NAME.match(name):
            raise StoreError("arrays", f"invalid array name {name!r} (letters, digits, _)")
        arr = np.asarray(value)
        if arr.dtype.kind not in "biufc":
            raise StoreError(f"arrays.{name}", f"must be numeric, got dtype {arr.dtype}")
        if arr.dtype.kind in "fc" and not np.all(np.isfinite(arr)):
            raise StoreError(f"arrays.{name}", "contains NaN or inf")
        out[name] = arr if arr.flags.c_contiguous else arr.copy(order="C")
    return out


def _attrs_json(attrs: Any) -> str:
    if attrs is None:
        attrs = {}
    if not isinstance(attrs, dict):
        raise StoreError("attrs", "must be a mapping")
    try:
        return json.dumps(attrs, sort_keys=True, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise StoreError("attrs", f"must be JSON-serialisable finite values: {exc}") from None


def _write_dataset(group: h5py.Group, name: str, arr: np.ndarray, compress_floats: bool = False) -> None:
    # fletcher32 needs chunked storage, impossible for 0-d and empty arrays: store those as
    # a (1,)-shaped / plain dataset and remember the shape.
    stored = arr.reshape(1) if arr.ndim == 0 else arr
    if stored.size == 0:
        dset = group.create_dataset(name, data=stored)
    else:
        compress = compress_floats or stored.dtype.kind in _INTEGER_KINDS
        dset = group.create_dataset(name, data=stored, fletcher32=True, chunks=True,
                                    shuffle=compress, compression="gzip" if compress else None,
                                    compression_opts=4 if compress else None)
    dset.attrs["shape"] = np.asarray(arr.shape, dtype=np.int64)


def _read_dataset(dset: h5py.Dataset) -> np.ndarray:
    shape = tuple(int(s) for s in dset.attrs["shape"])
    return np.asarray(dset[()]).reshape(shape)


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _fsync_directory(directory: Path) -> None:
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return  # not supported on this platform/filesystem
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _utc_now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


class ModelStore:
    """A directory of ``<id>.h5`` model files (other names are ignored).

    ``compress_floats``: also gzip the float arrays when saving (smaller, slower to load).
    """

    def __init__(self, directory: str | os.PathLike, compress_floats: bool = False):
        self.directory = Path(directory)
        self.compress_floats = bool(compress_floats)

    # -- names ----------------------------------------------------------------------
    def path(self, model_id_: str) -> Path:
        if not isinstance(model_id_, str) or not _ID.match(model_id_):
            raise NotFound("model_id", f"{model_id_!r} is not a model id ({ID_LENGTH} hex digits)")
        return self.directory / f"{model_id_}{SUFFIX}"

    def exists(self, model_id_: str) -> bool:
        try:
            return self.path(model_id_).is_file()
        except NotFound:
            return False

    def ids(self) -> list[str]:
        if not self.directory.is_dir():
            return []
        names = (p.name for p in self.directory.iterdir())
        return sorted(n[: -len(SUFFIX)] for n in names if n.endswith(SUFFIX) and _ID.match(n[: -len(SUFFIX)]))

    # -- writing --------------------------------------------------------------------
    def save(self, spec_json: str, arrays: dict[str, Any], attrs: dict[str, Any] | None = None,
             lazy: dict[str, Any] | None = None) -> str:
        """Write the model atomically and return its id (an existing file is replaced); ``lazy``:
        (K, ...) arrays stored to be read one row at a time (module docstring)."""
        checked = _checked_arrays(arrays)
        lazy = _checked_arrays(lazy or {})
        for name, arr in lazy.items():
            if arr.ndim < 1 or arr.shape[0] < 1 or name in checked:
                raise StoreError(f"lazy.{name}",
                                 "must be a (K, ...) array with K >= 1, named apart from the arrays")
        _attrs_json(attrs)  # refused before anything is written
        with self.writer(spec_json) as writer:
            writer.arrays_by_row(lazy)
            return writer.finish(checked, attrs)

    def writer(self, spec_json: str) -> "ModelWriter":
        """A model file written in parts (``with store.writer(spec) as w: w.row(...); w.finish(...)``):
        the rows of the lazy arrays as they are computed (an atlas, centre by centre, so they never all
        sit in memory), then the arrays; the file appears under its id only at ``finish``, and a writer
        left without it (an error, an interrupt) leaves nothing behind."""
        spec = canonical_spec(spec_json)
        self.ensure_writable()
        self.clean_stale_temporaries()
        return ModelWriter(self, spec)

    def ensure_writable(self) -> None:
        """Create the directory if needed; StoreError('store') unless files can be written there."""
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise StoreError("store", f"cannot create directory {self.directory}: {exc}") from None
        if not os.access(self.directory, os.W_OK | os.X_OK):
            raise StoreError("store", f"directory {self.directory} is not writable")

    def clean_stale_temporaries(self) -> list[str]:
        """Remove temporary files whose writer process (on this host) no longer runs."""
        removed = []
        if not self.directory.is_dir():
            return removed
        for entry in self.directory.iterdir():
            match = _TMP.match(entry.name)
            if match and not _pid_alive(int(match.group(1))):
                try:
                    entry.unlink()
                    removed.append(entry.name)
                except OSError:
                    pass  # another cleaner got there first, or no permission: harmless
        return removed

    def delete(self, model_id_: str) -> None:
        path = self.path(model_id_)
        try:
            path.unlink()
        except FileNotFoundError:
            raise NotFound("model_id", f"no model {model_id_} in {self.directory}") from None
        except OSError as exc:
            raise StoreError("store", f"cannot delete {path.name}: {exc}") from None

    # -- reading --------------------------------------------------------------------
    def load(self, model_id_: str) -> StoredModel:
        """Read and verify a model: format version, id = hash of the stored spec, checksums."""
        path = self.path(model_id_)
        if not path.is_file():
            raise NotFound("model_id", f"no model {model_id_} in {self.directory}")
        try:
            with h5py.File(path, "r") as h5:
                return _verified(h5, model_id_, path)
        except StoreError:
            raise
        except (OSError, KeyError, ValueError, TypeError, RuntimeError) as exc:
            message = f"model file {path.name} is corrupt or unreadable: {_short(exc)}"
            raise StoreError("model", message) from None

    def list(self) -> list[ModelSummary]:
        """Summaries of every stored model, from the file attributes (datasets are not read)."""
        return [self.summary(mid) for mid in self.ids()]

    def summary(self, mid: str) -> ModelSummary:
        """The summary of model ``mid`` stored in its file's attributes (a file written before summaries
        were stored: computed from its stored spec); ``error`` set when the file cannot be read."""
        path = self.path(mid)
        try:
            size = path.stat().st_size
            with h5py.File(path, "r") as h5:
                _check_version(h5, mid)
                spec_text = _text_attr(h5, "spec")
                created = _text_attr(h5, "created")
                attrs = json.loads(_text_attr(h5, "attrs"))
                fields = attrs.get("summary") if isinstance(attrs, dict) else None
                if not isinstance(fields, dict):  # written before summaries were stored: from the spec
                    fields = spec_summary(json.loads(spec_text), _basis_shape(h5), attrs)
        except FileNotFoundError:
            return ModelSummary(id=mid, error="deleted while listing")
        except (OSError, KeyError, ValueError, TypeError, RuntimeError, StoreError) as exc:
            return ModelSummary(id=mid, file_size=_size_or_zero(path), error=_short(exc))
        held = model_id(spec_text)
        if held != mid:  # a file renamed or swapped: its spec hashes to another id
            swapped = f"the file holds model {held}, not {mid} (renamed or swapped); not served"
            return ModelSummary(id=mid, file_size=size, error=swapped)
        return ModelSummary(id=mid, **{key: fields.get(key) for key in SUMMARY_FIELDS}, created=created,
                            file_size=size,
                            extra={key: attrs[key] for key in ("method", "method_reason") if key in attrs})


class ModelWriter:
    """One model file being written (:meth:`ModelStore.writer`): a hidden temporary file in the store's
    directory until :meth:`finish` verifies that every lazy row was written, records the hashes and
    ``os.replace``s it under the model's id."""

    def __init__(self, store: ModelStore, spec: str):
        self.store, self.spec, self.id = store, spec, model_id(spec)
        self.tmp = store.directory / f"{TMP_PREFIX}{self.id}-{os.getpid()}-{secrets.token_hex(4)}{SUFFIX}"
        self._rows: dict[str, tuple[tuple[int, ...], str, list[str | None]]] = {}
        self._h5: h5py.File | None = None

    def __enter__(self) -> "ModelWriter":
        try:
            self._h5 = h5py.File(self.tmp, "w-")
        except OSError as exc:
            raise StoreError("store", f"cannot write model to {self.store.directory}: {exc}") from None
        return self

    def __exit__(self, kind, exc, traceback) -> None:
        if self._h5 is not None:  # not finished: an error or an interrupt; nothing stays
            self._h5.close()
            self._h5 = None
            self.tmp.unlink(missing_ok=True)

    def row(self, name: str, k: int, count: int, value: Any) -> None:
        """Row k of the lazy (count, ...) array ``name`` (the first row written fixes its shape and
        dtype; rows may come in any order, each once)."""
        if self._h5 is None:
            raise StoreError("store", "the writer is closed (use it inside its with block, before finish)")
        arr = _checked_arrays({name: value})[name]
        found = self._rows.get(name)
        if found is None:
            if not isinstance(count, int) or count < 1:
                raise StoreError(f"lazy.{name}", f"needs a row count >= 1, got {count!r}")
            group = self._h5.require_group("lazy")
            shape = (count,) + arr.shape
            group.create_dataset(name, shape=shape, dtype=arr.dtype, chunks=(1,) + arr.shape, fletcher32=True)
            found = self._rows[name] = (shape, arr.dtype.str, [None] * count)
        shape, dtype, hashes = found
        if count != shape[0] or arr.shape != shape[1:] or arr.dtype.str != dtype:
            raise StoreError(f"lazy.{name}", f"row {k} is {arr.shape} {arr.dtype.str} of {count}, the array "
                                             f"is {shape} {dtype}")
        if not isinstance(k, (int, np.integer)) or isinstance(k, bool):
            raise StoreError(f"lazy.{name}", f"a row index must be an integer, got {k!r}")
        k = int(k)
        if not 0 <= k < count:
            raise StoreError(f"lazy.{name}", f"row {k} is out of range (0..{count - 1})")
        if hashes[k] is not None:
            raise StoreError(f"lazy.{name}", f"row {k} was written twice")
        try:
            self._h5["lazy"][name][k] = arr
        except OSError as exc:
            raise StoreError("store", f"cannot write model to {self.store.directory}: {exc}") from None
        hashes[k] = hashlib.sha256(arr.tobytes()).hexdigest()

    def rows(self, k: int, count: int, values: dict[str, Any]) -> None:
        """Row k of each lazy (count, ...) array named in ``values`` (an atlas centre's arrays)."""
        for name, value in values.items():
            self.row(name, k, count, value)

    def arrays_by_row(self, arrays: dict[str, Any]) -> None:
        """Every row of each whole (K, ...) lazy array in ``arrays``."""
        for name, arr in arrays.items():
            for k, row in enumerate(arr):
                self.row(name, k, len(arr), row)

    def finish(self, arrays: dict[str, Any], attrs: dict[str, Any] | None = None) -> str:
        """Write the arrays and the attributes, check that every lazy row is there, and put the file
        in place atomically; returns the model id."""
        if self._h5 is None:
            raise StoreError("store", "the writer is closed (finish is called once)")
        checked = _checked_arrays(arrays)
        _attrs_json(attrs)  # the caller's attrs, checked as they are given
        basis = checked["basis"].shape if "basis" in checked else None
        summary = spec_summary(json.loads(self.spec), basis, attrs)  # computed once, here, for every listing
        attrs_text = _attrs_json({**(attrs or {}), "summary": summary})
        for name, (shape, _, hashes) in self._rows.items():
            if name in checked:
                raise StoreError(f"lazy.{name}", "must be named apart from the arrays")
            if None in hashes:
                raise StoreError(f"lazy.{name}", f"row {hashes.index(None)} of {shape[0]} was never written")
        h5, self._h5 = self._h5, None
        try:
            self._close(h5, checked, attrs_text)
            os.replace(self.tmp, self.store.path(self.id))
        except OSError as exc:
            self.tmp.unlink(missing_ok=True)
            raise StoreError("store", f"cannot write model to {self.store.directory}: {exc}") from None
        except BaseException:
            self.tmp.unlink(missing_ok=True)
            raise
        _fsync_directory(self.store.directory)
        return self.id

    def _close(self, h5: h5py.File, arrays: dict[str, np.ndarray], attrs: str) -> None:
        try:
            created, versions = _utc_now(), json.dumps(library_versions(), sort_keys=True)
            h5.attrs["format_version"] = FORMAT_VERSION
            h5.attrs["model_id"] = self.id
            h5.attrs["spec"] = self.spec
            h5.attrs["created"] = created
            h5.attrs["versions"] = versions
            h5.attrs["attrs"] = attrs
            h5.attrs["meta_sha256"] = _meta_digest(self.spec, attrs, created, versions,
                                                   _layout(arrays) + _lazy_layout(self._rows))
            group = h5.create_group("arrays")
            for name, arr in arrays.items():
                _write_dataset(group, name, arr, self.store.compress_floats)
            for name, (_, _, hashes) in self._rows.items():
                h5["lazy"][name].attrs["row_sha256"] = np.array(hashes, dtype="S64")
        finally:
            h5.close()
        fd = os.open(self.tmp, os.O_RDONLY)
        try:
            os.fsync(fd)  # the bytes are on disk before the rename makes them visible
        finally:
            os.close(fd)


def spec_summary(spec: dict, basis_shape: tuple | None, attrs: dict | None = None) -> dict[str, Any]:
    """A model's summary (:data:`SUMMARY_FIELDS`) from its spec document, the shape of its ``basis``
    array (None: no such array; the spec's basis size then) and its attrs (``offline`` false: a
    mesh-free model, basis 0 whatever the spec says)."""
    disc = spec.get("discretization") or {}
    domain = spec.get("domain") or {}
    basis = int(basis_shape[-1]) if basis_shape else disc.get("basis")
    if (attrs or {}).get("offline") is False:  # a mesh-free model (yau-jia): no basis, whatever the spec says
        basis = 0
    state, obs = spec.get("state"), spec.get("observation")
    return {"name": spec.get("name"), "state": state if isinstance(state, list) else None,
            "n": len(state) if isinstance(state, list) else None,
            "m": len(obs) if isinstance(obs, list) else None, "dt": disc.get("dt"),
            "radius": domain.get("radius"), "basis": basis, "follow": bool(domain.get("follow", False)),
            "region": domain.get("region"), "shape": domain.get("shape")}


def _basis_shape(h5: h5py.File) -> tuple | None:
    group = h5.get("arrays")
    if group is None or "basis" not in group:
        return None
    return tuple(int(s) for s in group["basis"].attrs["shape"])


def _size_or_zero(path: Path) -> int:
    try:
        return path.stat().st_size
    except OSError:
        return 0


def _short(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return (text[0] if text else type(exc).__name__)[:300]


def _text_attr(h5: h5py.File, name: str) -> str:
    value = h5.attrs[name]
    if isinstance(value, bytes):
        value = value.decode("utf-8")
    if not isinstance(value, str):
        raise StoreError("model", f"attribute {name!r} is not text")
    return value


def _check_version(h5: h5py.File, mid: str) -> None:
    version = h5.attrs.get("format_version")
    if version is None or int(version) != FORMAT_VERSION:
        hint = (": re-run `yauyau precompute SPEC` (the spec is kept in the file: `h5dump -a spec`)"
                if version is not None and int(version) < FORMAT_VERSION else "")
        raise StoreError("format_version",
                         f"model {mid} has format version {version}, this library reads "
                         f"{FORMAT_VERSION}{hint}")


def _verified(h5: h5py.File, mid: str, path: Path | None = None) -> StoredModel:
    _check_version(h5, mid)
    spec = _text_attr(h5, "spec")
    try:
        actual = model_id(spec)
    except StoreError:
        actual = None
    if actual != mid:
        raise StoreError("model", f"file {mid}{SUFFIX} does not hold model {mid} (spec hashes to {actual})")
    attrs_text, created, versions = (_text_attr(h5, k) for k in ("attrs", "created", "versions"))
    group = h5["arrays"]
    arrays = {name: _read_dataset(group[name]) for name in group}  # reading verifies fletcher32
    rows = {name: (tuple(int(s) for s in dset.shape), dset.dtype.str,
                   [bytes(h).decode("ascii") for h in dset.attrs["row_sha256"]])
            for name, dset in h5.get("lazy", {}).items()}
    digest = _meta_digest(spec, attrs_text, created, versions, _layout(arrays) + _lazy_layout(rows))
    if digest != _text_attr(h5, "meta_sha256"):
        raise StoreError("model", f"model {mid}: checksum mismatch of the metadata or arrays (file altered)")
    attrs = dict(json.loads(attrs_text))
    attrs.update(format_version=FORMAT_VERSION, created=created, versions=json.loads(versions))
    lazy = LazyArrays(Path(path if path is not None else h5.filename), rows) if rows else None
    return StoredModel(id=mid, spec_json=spec, arrays=arrays, attrs=attrs, lazy=lazy)

"""HDF5 model store: round trip, atomic writes under SIGKILL, and refusal of damaged files."""

from __future__ import annotations

import hashlib
import importlib.metadata
import json
import os
import random
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import h5py
import numpy as np
import pytest
from helpers import ROOT
from yauyau.solver.spec import load_spec
from yauyau.storage.errors import NotFound, StoreError
from yauyau.storage.model_store import FORMAT_VERSION, ModelStore, model_id

SPEC = json.dumps({"name": "ou", "state": ["x"], "observation": ["x"], "drift": ["-x"],
                   "domain": {"radius": 8.0}, "discretization": {"dt": 0.01, "basis": 6}})


def _arrays(rng: np.random.Generator) -> dict[str, np.ndarray]:
    return {"basis": rng.standard_normal((40, 6)), "propagator_fp": rng.standard_normal((40, 6)),
            "mesh_cells": np.arange(78, dtype=np.int64).reshape(2, 39), "eigenvalues": -np.arange(6.0),
            "weights": np.full(40, 0.4, dtype=np.float32)}


@pytest.fixture
def store(tmp_path: Path) -> ModelStore:
    return ModelStore(tmp_path / "models")


def test_id_is_sha256_of_canonical_spec_and_format_version():
    doc = json.loads(SPEC)
    shuffled = json.dumps(dict(reversed(list(doc.items()))), indent=3)
    canonical = json.dumps(doc, sort_keys=True, separators=(",", ":"))
    expected = hashlib.sha256(f"yauyau-model/{FORMAT_VERSION}\n{canonical}".encode()).hexdigest()[:20]
    assert model_id(SPEC) == model_id(shuffled) == expected
    other = dict(doc, discretization={"dt": 0.01, "basis": 7})
    assert model_id(json.dumps(other)) != model_id(SPEC)


def test_id_follows_the_solver_canonical_json_including_discretization():
    spec = load_spec(ROOT / "examples" / "ou.toml")
    finer = spec.model_copy(update={"discretization": spec.discretization.model_copy(update={"basis": 32})})
    assert model_id(spec.canonical_json()) == model_id(spec.canonical_json())
    assert model_id(spec.canonical_json()) != model_id(finer.canonical_json())


def test_round_trip_preserves_arrays_bitwise_spec_and_attrs(store: ModelStore):
    arrays = _arrays(np.random.default_rng(1))
    mid = store.save(SPEC, arrays, {"seconds": 1.5, "method": "yau-yau"})
    assert mid == model_id(SPEC) and store.path(mid).is_file()
    loaded = store.load(mid)
    assert loaded.id == mid and json.loads(loaded.spec_json) == json.loads(SPEC)
    assert set(loaded.arrays) == set(arrays)
    for name, arr in arrays.items():
        assert loaded.arrays[name].dtype == arr.dtype and loaded.arrays[name].shape == arr.shape
        assert np.array_equal(loaded.arrays[name], arr)
    assert loaded.attrs["seconds"] == 1.5 and loaded.attrs["method"] == "yau-yau"
    assert loaded.attrs["format_version"] == FORMAT_VERSION
    assert loaded.attrs["versions"]["numpy"] == importlib.metadata.version("numpy")
    assert loaded.attrs["versions"]["scikit-fem"] == importlib.metadata.version("scikit-fem")
    assert loaded.attrs["created"].endswith("+00:00")
    with h5py.File(store.path(mid), "r") as h5:
        assert all(h5["arrays"][k].fletcher32 for k in arrays)


def test_compressed_floats_round_trip_bitwise_and_are_gzipped(tmp_path: Path):
    store = ModelStore(tmp_path, compress_floats=True)
    arrays = _arrays(np.random.default_rng(11))
    loaded = store.load(store.save(SPEC, arrays))
    assert all(np.array_equal(loaded.arrays[k], v) for k, v in arrays.items())
    with h5py.File(store.path(model_id(SPEC)), "r") as h5:
        assert h5["arrays"]["basis"].compression == "gzip" and h5["arrays"]["basis"].fletcher32
    plain = ModelStore(tmp_path / "plain")
    with h5py.File(plain.path(plain.save(SPEC, arrays)), "r") as h5:
        assert h5["arrays"]["basis"].compression is None and h5["arrays"]["mesh_cells"].compression == "gzip"


def test_scalar_and_empty_arrays_round_trip(store: ModelStore):
    mid = store.save(SPEC, {"dt": np.float64(0.25), "none": np.zeros((0, 3))})
    loaded = store.load(mid).arrays
    assert loaded["dt"].shape == () and float(loaded["dt"]) == 0.25
    assert loaded["none"].shape == (0, 3)


def test_list_reads_summaries_and_ignores_other_files(store: ModelStore):
    mid = store.save(SPEC, _arrays(np.random.default_rng(2)))
    (store.directory / "README.txt").write_text("not a model")
    (store.directory / "notes.h5").write_bytes(b"junk")
    [summary] = store.list()
    assert (summary.id, summary.name, summary.n, summary.m) == (mid, "ou", 1, 1)
    assert (summary.dt, summary.radius, summary.basis) == (0.01, 8.0, 6)
    assert summary.file_size == store.path(mid).stat().st_size and summary.error is None


def test_missing_and_malformed_ids_are_not_found(store: ModelStore):
    assert store.list() == []
    with pytest.raises(NotFound, match="no model"):
        store.load("0" * 20)
    with pytest.raises(NotFound, match="not a model id"):
        store.load("../../etc/passwd")


def _flip_byte(path: Path, offset: int) -> None:
    with open(path, "r+b") as fh:
        fh.seek(offset)
        byte = fh.read(1)
        fh.seek(offset)
        fh.write(bytes([byte[0] ^ 0x5A]))


def test_flipped_byte_inside_dataset_data_is_refused(store: ModelStore):
    mid = store.save(SPEC, _arrays(np.random.default_rng(3)))
    with h5py.File(store.path(mid), "r") as h5:
        info = h5["arrays"]["propagator_fp"].id.get_chunk_info(0)
    _flip_byte(store.path(mid), info.byte_offset + info.size // 2)
    with pytest.raises(StoreError, match="corrupt") as err:
        store.load(mid)
    assert err.value.field == "model" and "Traceback" not in str(err.value)


@pytest.mark.slow
def test_every_single_bit_flip_is_refused_or_harmless(store: ModelStore):
    """Flip one bit anywhere (400 seeded positions): load refuses, or returns the original exactly.

    Bits in the chunk index are not covered by fletcher32 (HDF5 then returns zeros for the
    chunk); the per-array sha256 in the metadata digest catches those.
    """
    arrays = {"basis": np.random.default_rng(0).standard_normal((40, 6)),
              "mesh_cells": np.arange(78).reshape(2, 39), "order": np.int64(2)}
    mid = store.save(SPEC, arrays, {"k": 1})
    path, good = store.path(mid), store.path(mid).read_bytes()
    rng, refused = random.Random(1), 0
    for _ in range(400):
        damaged = bytearray(good)
        damaged[rng.randrange(len(good))] ^= 1 << rng.randrange(8)
        path.write_bytes(bytes(damaged))
        try:
            loaded = store.load(mid)
        except StoreError:
            refused += 1
            continue
        assert set(loaded.arrays) == set(arrays) and loaded.attrs["k"] == 1
        for name, arr in arrays.items():
            assert loaded.arrays[name].dtype == arr.dtype and np.array_equal(loaded.arrays[name], arr)
    assert refused > 40  # the flips did land in checked places


def test_edited_attribute_is_refused(store: ModelStore):
    mid = store.save(SPEC, _arrays(np.random.default_rng(4)), {"seconds": 1.0})
    with h5py.File(store.path(mid), "r+") as h5:
        h5.attrs["attrs"] = json.dumps({"seconds": 2.0})
    with pytest.raises(StoreError, match="checksum"):
        store.load(mid)


def _edit_attrs(path: Path, change) -> None:
    """Rewrite a file's ``attrs`` JSON in place (the listing reads it; ``load`` would now refuse the file)."""
    with h5py.File(path, "r+") as h5:
        attrs = json.loads(h5.attrs["attrs"])
        change(attrs)
        h5.attrs["attrs"] = json.dumps(attrs, sort_keys=True)


def test_the_summary_is_stored_once_and_read_by_every_listing(store: ModelStore):
    """Written with the file (attrs["summary"]) and read back by ``list()``; a file written before
    summaries were stored (none in its attrs) is listed from its spec."""
    mid = store.save(SPEC, _arrays(np.random.default_rng(3)), {"method": "yau-yau"})
    truth = {"name": "ou", "state": ["x"], "n": 1, "m": 1, "dt": 0.01, "radius": 8.0, "basis": 6,
             "follow": False, "region": None, "shape": None}
    assert store.load(mid).attrs["summary"] == truth
    _edit_attrs(store.path(mid), lambda attrs: attrs["summary"].update(name="renamed"))
    [summary] = store.list()
    assert (summary.name, summary.n, summary.basis, summary.extra["method"]) == ("renamed", 1, 6, "yau-yau")
    _edit_attrs(store.path(mid), lambda attrs: attrs.pop("summary"))  # as yauyau 0.2.0 wrote it
    [legacy] = store.list()
    assert {key: getattr(legacy, key) for key in truth} == truth and legacy.error is None


def test_truncated_file_is_refused_and_listed_with_an_error(store: ModelStore):
    mid = store.save(SPEC, _arrays(np.random.default_rng(5)))
    path = store.path(mid)
    os.truncate(path, path.stat().st_size // 2)
    with pytest.raises(StoreError, match="corrupt or unreadable"):
        store.load(mid)
    [summary] = store.list()
    assert summary.id == mid and summary.error


def test_non_hdf5_file_under_a_model_name_is_refused(store: ModelStore):
    store.directory.mkdir(parents=True)
    fake = store.directory / ("ab" * 10 + ".h5")
    fake.write_text("hello, not HDF5")
    with pytest.raises(StoreError, match="corrupt or unreadable"):
        store.load("ab" * 10)


def test_file_renamed_to_another_id_is_refused(store: ModelStore):
    mid = store.save(SPEC, _arrays(np.random.default_rng(6)))
    other = model_id(json.dumps(dict(json.loads(SPEC), name="other")))
    os.replace(store.path(mid), store.path(other))
    with pytest.raises(StoreError, match=f"does not hold model {other}"):
        store.load(other)


def test_a_file_of_yauyau_0_1_says_re_run_precompute(store: ModelStore):
    """Format 1 (no method stored) is refused with the fix named, not loaded without its method."""
    mid = store.save(SPEC, _arrays(np.random.default_rng(8)))
    with h5py.File(store.path(mid), "r+") as h5:
        h5.attrs["format_version"] = 1
    with pytest.raises(StoreError, match="re-run `yauyau precompute SPEC`") as err:
        store.load(mid)
    assert err.value.field == "format_version" and FORMAT_VERSION == 2


def test_wrong_format_version_is_refused(store: ModelStore):
    mid = store.save(SPEC, _arrays(np.random.default_rng(7)))
    with h5py.File(store.path(mid), "r+") as h5:
        h5.attrs["format_version"] = FORMAT_VERSION + 1
    with pytest.raises(StoreError, match="format version") as err:
        store.load(mid)
    assert err.value.field == "format_version"
    assert store.list()[0].error


@pytest.mark.parametrize("arrays, field", [
    ({"bad name": np.ones(2)}, "arrays"),
    ({"nan": np.array([1.0, np.nan])}, "arrays.nan"),
    ({"text": np.array(["a"])}, "arrays.text"),
])
def test_bad_arrays_are_refused_before_writing(store: ModelStore, arrays, field):
    with pytest.raises(StoreError) as err:
        store.save(SPEC, arrays)
    assert err.value.field == field
    assert not store.directory.exists() or not any(store.directory.iterdir())


def test_unwritable_directory_is_a_store_error(tmp_path: Path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(StoreError) as err:
        ModelStore(blocker / "models").save(SPEC, {"a": np.ones(3)})
    assert err.value.field == "store"


_KILLED_WRITER = textwrap.dedent("""
    import sys, time
    import numpy as np
    import yauyau.storage.model_store as ms

    original = ms._write_dataset
    def slow_write(group, name, arr, *options):
        original(group, name, arr, *options)
        group.file.flush()
        print("WRITING", flush=True)   # one dataset is on disk, the next one never will be
        time.sleep(60)
    ms._write_dataset = slow_write
    ms.ModelStore(sys.argv[1]).save(sys.argv[2], {"big": np.ones((512, 1024)), "more": np.ones(8)})
""")


def test_write_killed_midway_leaves_no_model_and_is_cleaned_up(store: ModelStore):
    proc = subprocess.Popen([sys.executable, "-c", _KILLED_WRITER, str(store.directory), SPEC],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT)
    try:
        assert proc.stdout.readline().strip() == "WRITING", proc.stderr.read()
        temporaries = [p for p in store.directory.iterdir() if p.name.startswith(".tmp-")]
        assert len(temporaries) == 1 and temporaries[0].stat().st_size > 4 * 1024 * 1024
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
    mid = model_id(SPEC)
    assert not store.path(mid).exists() and store.list() == []
    with pytest.raises(NotFound):
        store.load(mid)
    assert store.save(SPEC, {"big": np.ones(4)}) == mid  # cleans the dead writer's leftovers
    assert sorted(p.name for p in store.directory.iterdir()) == [f"{mid}.h5"]
    assert np.array_equal(store.load(mid).arrays["big"], np.ones(4))


def test_live_writers_temporaries_are_not_removed(store: ModelStore):
    store.directory.mkdir(parents=True)
    live = store.directory / f".tmp-{'c' * 20}-{os.getpid()}-abcd.h5"
    live.write_bytes(b"in progress")
    assert store.clean_stale_temporaries() == []
    assert live.exists()


def test_saving_an_existing_model_replaces_it_atomically(store: ModelStore):
    mid = store.save(SPEC, {"a": np.zeros(3)})
    assert store.save(SPEC, {"a": np.ones(3)}) == mid
    assert np.array_equal(store.load(mid).arrays["a"], np.ones(3))
    assert [p.name for p in store.directory.iterdir()] == [f"{mid}.h5"]


def _lazy(rng: np.random.Generator) -> dict[str, np.ndarray]:
    return {"atlas_propagator_fp": rng.standard_normal((5, 40, 6)),
            "atlas_generator": rng.standard_normal((5, 6, 6))}


def test_rows_written_as_they_come_give_the_file_save_writes(store: ModelStore):
    """Truth: the arrays themselves, and a file written by ``save`` in one go.  The writer takes the
    rows in any order; nothing is under the model's id before ``finish``."""
    rng = np.random.default_rng(3)
    arrays, lazy = _arrays(rng), _lazy(rng)
    with store.writer(SPEC) as writer:
        for k in (3, 0, 4, 1, 2):
            writer.rows(k, 5, {name: arr[k] for name, arr in lazy.items()})
        assert not store.exists(writer.id) and writer.tmp.exists()
        mid = writer.finish(arrays, {"a": 1})
    streamed = store.load(mid)
    other = ModelStore(store.directory.parent / "other")
    whole = other.load(other.save(SPEC, arrays, {"a": 1}, lazy=lazy))
    for name, arr in arrays.items():
        assert np.array_equal(streamed.arrays[name], arr) and streamed.arrays[name].dtype == arr.dtype
    for name, arr in lazy.items():
        assert streamed.lazy.shape(name) == whole.lazy.shape(name) == arr.shape
        for k in range(5):
            assert np.array_equal(streamed.lazy.read(name, k), arr[k])
    with h5py.File(store.path(mid), "r") as a, h5py.File(other.path(mid), "r") as b:
        for name in lazy:
            assert np.array_equal(a["lazy"][name].attrs["row_sha256"], b["lazy"][name].attrs["row_sha256"])
            assert a["lazy"][name].chunks == b["lazy"][name].chunks and a["lazy"][name].fletcher32
    assert [p.name for p in store.directory.iterdir()] == [f"{mid}.h5"]


def test_a_writer_that_misses_a_row_or_fails_leaves_nothing(store: ModelStore):
    rng = np.random.default_rng(4)
    arrays, lazy = _arrays(rng), _lazy(rng)
    with pytest.raises(StoreError) as missing:
        with store.writer(SPEC) as writer:
            for k in (0, 1, 3, 4):
                writer.rows(k, 5, {name: arr[k] for name, arr in lazy.items()})
            writer.finish(arrays)
    assert missing.value.field.startswith("lazy.") and "row 2 of 5 was never written" in missing.value.message
    with pytest.raises(StoreError) as wrong:
        with store.writer(SPEC) as writer:
            writer.row("atlas_generator", 0, 5, lazy["atlas_generator"][0])
            writer.row("atlas_generator", 1, 5, lazy["atlas_generator"][1, :5])  # a row of another shape
    assert wrong.value.field == "lazy.atlas_generator" and "(5, 6)" in wrong.value.message
    with pytest.raises(StoreError, match="written twice"):
        with store.writer(SPEC) as writer:
            writer.row("atlas_generator", 0, 5, lazy["atlas_generator"][0])
            writer.row("atlas_generator", 0, 5, lazy["atlas_generator"][0])
    for k, words in ((5, "out of range"), (-1, "out of range"), (1.0, "must be an integer")):
        with pytest.raises(StoreError, match=words):
            with store.writer(SPEC) as writer:
                writer.row("atlas_generator", np.int64(0), 5, lazy["atlas_generator"][0])  # numpy ints do
                writer.row("atlas_generator", k, 5, lazy["atlas_generator"][1])
    with pytest.raises(KeyboardInterrupt):  # an interrupt mid-computation
        with store.writer(SPEC) as writer:
            writer.row("atlas_generator", 0, 5, lazy["atlas_generator"][0])
            raise KeyboardInterrupt
    assert list(store.directory.iterdir()) == [] and not store.exists(model_id(SPEC))

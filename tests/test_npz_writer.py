"""wire/npz_writer.py: an .npz that np.load, zipfile (its CRCs) and our own bounded reader take
as np.savez's, for every kind of array a checkpoint holds."""

from __future__ import annotations

import io
import zipfile

import numpy as np
import pytest

from fleetslam.wire import npz_reader, npz_writer
from fleetslam.wire.npz_writer import write_npz

RNG = np.random.default_rng(5)
ARRAYS = {
    "ints": np.arange(-5, 10, dtype=np.int64),
    "transposed": RNG.random((5, 3)).T,  # not C-contiguous
    "strided": RNG.integers(0, 255, (7, 32), dtype=np.uint8)[:, ::2],
    "scalar": np.array(5.0),  # 0-d stays 0-d
    "empty": np.zeros((0, 4)),
    "flags": np.array([True, False, True]),
    "complex": RNG.random(4) + 1j,
    "half": np.float16([1.5, -2.0]),
    "poses": RNG.random((3, 4, 4)),
}


def _same(got: dict, expected: dict) -> None:
    assert list(got) == list(expected)
    for name, array in expected.items():
        assert got[name].dtype == array.dtype and got[name].shape == array.shape, name
        np.testing.assert_array_equal(got[name], array)


def test_what_np_load_and_our_reader_read_is_what_was_written():
    blob = write_npz(ARRAYS)
    with np.load(io.BytesIO(blob)) as loaded:
        _same({name: loaded[name] for name in loaded.files}, ARRAYS)
    _same(npz_reader.read_npz(blob, 1 << 20, {}), ARRAYS)
    assert npz_reader.layout_problem(io.BytesIO(blob), len(blob)) is None  # nothing unaccounted
    with zipfile.ZipFile(io.BytesIO(blob)) as z:
        assert z.testzip() is None  # every member's CRC is right
        assert [i.compress_type for i in z.infolist()] == [zipfile.ZIP_STORED] * len(ARRAYS)


def test_the_members_are_np_saves_npy_files():
    blob = write_npz(ARRAYS)
    reference = io.BytesIO()
    np.savez(reference, **ARRAYS)
    with zipfile.ZipFile(io.BytesIO(blob)) as ours, zipfile.ZipFile(reference) as numpy_s:
        for name in ARRAYS:
            assert ours.read(f"{name}.npy") == numpy_s.read(f"{name}.npy"), name


def test_more_members_than_a_plain_zip_counts_are_written_as_zip64(monkeypatch):
    # A plain zip counts 65535 members; here the count is lowered to keep the test quick.
    monkeypatch.setattr(npz_writer, "_ZIP32_MEMBERS", 3)
    blob = write_npz(ARRAYS)
    _same(npz_reader.read_npz(blob, 1 << 20, {}), ARRAYS)
    assert blob[4:6] == (45).to_bytes(2, "little")  # "version 4.5 needed": zip64 members
    assert write_npz(dict(list(ARRAYS.items())[:3]))[4:6] == (20).to_bytes(2, "little")


def test_an_object_array_is_refused():
    with pytest.raises(TypeError, match="objects"):
        write_npz({"bad": np.array([{}, []], dtype=object)})

"""Writing an ``.npz`` as ``np.savez`` does (a zip of stored ``.npy`` members, readable by
``np.load`` and npz_reader.py), in one pass over the arrays' bytes.

Why not ``np.savez``: it writes each member through ``zipfile`` in Python, and a session
checkpoint has ~450 arrays: 12 ms of the worker's GIL for a 6 MB checkpoint of a 600-frame
map (bench/worker_scaling.py: the checkpoints' encoding was 19 % of a worker's GIL time
with 10 robots). Here each member is its ``.npy`` header and the array's own buffer,
joined once; ``zlib.crc32`` lets the GIL go on large buffers.
"""

from __future__ import annotations

import io
import struct
import zlib

import numpy as np

# A plain zip (no zip64): every offset and size must fit 32 bits, and the member count 16;
# larger goes to np.savez (which writes zip64).
_ZIP32_LIMIT = 0xFFFFFFFF
_ZIP32_MEMBERS = 0xFFFF
# DOS date and time of 1980-01-01 00:00 (the members' time carries no meaning here).
_DOS_TIME, _DOS_DATE = 0, (0 << 9) | (1 << 5) | 1
_VERSION = 20  # "2.0": stored members, no zip64


def _npy_header(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        buffer, np.lib.format.header_data_from_array_1_0(array))
    return buffer.getvalue()


def write_npz(arrays: dict[str, np.ndarray]) -> bytes:
    """The ``.npz`` of ``arrays`` (member ``<name>.npy`` each, in this order)."""
    members: list[tuple[bytes, bytes, memoryview]] = []
    total = 0
    for name, array in arrays.items():
        array = np.asarray(array)
        if array.dtype.hasobject:
            raise TypeError(f"array {name!r} holds objects")
        if not array.flags.c_contiguous and not array.flags.f_contiguous:
            array = array.copy(order="C")  # (a 0-d array stays 0-d)
        header = _npy_header(array)  # says Fortran order for an F-contiguous one, as numpy
        in_memory = array.T if not array.flags.c_contiguous else array
        data = memoryview(in_memory.reshape(-1).view(np.uint8))  # its bytes, not a copy
        members.append((f"{name}.npy".encode(), header, data))
        total += len(members[-1][0]) * 2 + len(members[-1][1]) + len(data) + 76
    if total > _ZIP32_LIMIT or len(members) > _ZIP32_MEMBERS:
        buffer = io.BytesIO()
        np.savez(buffer, **arrays)
        return buffer.getvalue()
    parts: list[bytes | memoryview] = []
    central: list[bytes] = []
    offset = 0
    for name, header, data in members:
        crc = zlib.crc32(data, zlib.crc32(header))
        size = len(header) + len(data)
        local = struct.pack("<IHHHHHIIIHH", 0x04034B50, _VERSION, 0, 0, _DOS_TIME, _DOS_DATE,
                            crc, size, size, len(name), 0) + name
        central.append(struct.pack("<IHHHHHHIIIHHHHHII", 0x02014B50, _VERSION, _VERSION, 0,
                                   0, _DOS_TIME, _DOS_DATE, crc, size, size, len(name), 0, 0,
                                   0, 0, 0o600 << 16, offset) + name)
        parts += [local, header, data]
        offset += len(local) + size
    directory = b"".join(central)
    end = struct.pack("<IHHHHIIH", 0x06054B50, 0, 0, len(central), len(central),
                      len(directory), offset, 0)
    return b"".join([*parts, directory, end])

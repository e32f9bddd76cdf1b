"""Binary little-endian PLY with xyz (float32) and optional rgb (uint8)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


def write_ply(path: str | Path, points: np.ndarray, colors: np.ndarray | None = None) -> None:
    """Write points (N, 3) and optional colours (N, 3) uint8 RGB as binary PLY."""
    points = np.asarray(points)
    n = len(points)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if colors is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    data = np.empty(n, dtype=fields)
    data["x"], data["y"], data["z"] = points[:, 0], points[:, 1], points[:, 2]
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {n}",
              "property float x", "property float y", "property float z"]
    if colors is not None:
        colors = np.asarray(colors, dtype=np.uint8)
        data["red"], data["green"], data["blue"] = colors[:, 0], colors[:, 1], colors[:, 2]
        header += ["property uchar red", "property uchar green", "property uchar blue"]
    header.append("end_header")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(data.tobytes())


def read_ply(path: str | Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Read the vertex element of a binary little-endian or ASCII PLY: (points (N, 3) float64,
    colours (N, 3) uint8 or None)."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise ValueError(f"{path}: cannot read PLY: {exc}") from exc
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        raise ValueError(f"{path}: not a PLY file (no 'ply' magic or 'end_header')")
    body_start = raw.index(b"\n", end) + 1
    header = raw[:end].decode("ascii", errors="replace").splitlines()
    fmt = None
    elements: list[tuple[str, int, list[tuple[str, str]]]] = []
    for line in header:
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "format":
            fmt = parts[1]
        elif parts[0] == "element":
            elements.append((parts[1], int(parts[2]), []))
        elif parts[0] == "property":
            if parts[1] == "list":
                raise ValueError(f"{path}: list properties before vertices are not supported")
            if parts[1] not in _PLY_TYPES:
                raise ValueError(f"{path}: unknown PLY property type '{parts[1]}'")
            elements[-1][2].append((parts[2], _PLY_TYPES[parts[1]]))
    if not elements or elements[0][0] != "vertex":
        raise ValueError(f"{path}: first PLY element is not 'vertex'")
    _, n, props = elements[0]
    names = [p[0] for p in props]
    if not {"x", "y", "z"} <= set(names):
        raise ValueError(f"{path}: vertex element lacks x, y, z")
    if fmt == "binary_little_endian":
        dtype = np.dtype([(name, "<" + t) for name, t in props])
        if len(raw) - body_start < n * dtype.itemsize:
            raise ValueError(f"{path}: truncated PLY ({n} vertices announced)")
        data = np.frombuffer(raw, dtype=dtype, count=n, offset=body_start)
        cols = {name: data[name] for name in names}
    elif fmt == "ascii":
        table = np.loadtxt(raw[body_start:].decode().splitlines()[:n], ndmin=2)
        cols = {name: table[:, i] for i, name in enumerate(names)}
    else:
        raise ValueError(f"{path}: unsupported PLY format '{fmt}'")
    points = np.stack([cols["x"], cols["y"], cols["z"]], axis=1).astype(np.float64)
    colors = None
    if {"red", "green", "blue"} <= set(names):
        colors = np.stack([cols["red"], cols["green"], cols["blue"]], axis=1).astype(np.uint8)
    return points, colors

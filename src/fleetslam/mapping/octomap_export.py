"""The global map as an OctoMap (``.bt``, read by octovis and every OctoMap library).

Each keyframe is one scan: its points are the occupied ends of rays cast from the keyframe's
camera centre, and the cells the rays cross are marked free (OctoMap's own ray casting).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Iterable

import numpy as np
import octomap


def build_octree(scans: Iterable[tuple[np.ndarray, np.ndarray]], resolution_m: float,
                 max_range_m: float) -> octomap.OcTree:
    """An octree from (points N x 3 in the map frame, sensor origin 3) scans."""
    tree = octomap.OcTree(resolution_m)
    for points, origin in scans:
        if len(points):
            tree.insertPointCloud(np.ascontiguousarray(points, dtype=np.float64),
                                  np.asarray(origin, dtype=np.float64), maxrange=max_range_m)
    tree.updateInnerOccupancy()
    return tree


def leaf_counts(tree: octomap.OcTree) -> tuple[int, int]:
    """(occupied, free) leaves."""
    occupied = free = 0
    for leaf in tree.begin_leafs():
        if tree.isNodeOccupied(leaf):
            occupied += 1
        else:
            free += 1
    return occupied, free


def write_octomap(path: Path, scans: Iterable[tuple[np.ndarray, np.ndarray]],
                  resolution_m: float, max_range_m: float) -> dict[str, Any]:
    """Build and write the octree (binary .bt); returns its counts and file size."""
    tree = build_octree(scans, resolution_m, max_range_m)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not tree.writeBinary(str(path).encode()):
        raise OSError(f"{path}: OctoMap could not write the file")
    occupied, free = leaf_counts(tree)
    return {"file": path.name, "resolution_m": resolution_m, "occupied": occupied,
            "free": free, "bytes": path.stat().st_size}


def read_octomap(path: Path) -> octomap.OcTree:
    """Load a ``.bt`` file (raises ValueError naming it if OctoMap cannot)."""
    if not Path(path).is_file():
        raise ValueError(f"{path}: no such OctoMap file")
    tree = octomap.OcTree(str(path).encode())
    if tree.getNumLeafNodes() == 0 and Path(path).stat().st_size > 0:
        raise ValueError(f"{path}: OctoMap read no nodes from it")
    return tree


# What OctoMap writes before a binary tree's data (writeBinary's header ends with this line).
_BINARY_DATA_LINE = b"\ndata\n"


def octomap_binary_data(path: Path) -> tuple[str, float, bytes]:
    """(tree id, resolution, data) of a ``.bt`` file as octomap_msgs carries a binary map:
    the tree's binary stream without the file's header, what OctoMap's ``writeBinaryData``
    writes and ``readBinaryData`` (octomap_msgs' ``binaryMsgToMap``) reads. Loaded and
    written again by OctoMap, so a file OctoMap cannot read is refused here."""
    tree = read_octomap(path)
    stream = tree.writeBinary()
    start = stream.find(_BINARY_DATA_LINE)
    if start < 0:
        raise ValueError(f"{path}: OctoMap wrote no 'data' line before the tree")
    return (tree.getTreeType().decode(), tree.getResolution(),
            stream[start + len(_BINARY_DATA_LINE):])

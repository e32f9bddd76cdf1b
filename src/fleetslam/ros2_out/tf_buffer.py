"""The robot's own TF tree as its ROS 2 graph publishes it (/tf and /tf_static), to place
fleetslam's map frame in it the way REP 105 asks of a SLAM node: where the camera's frame
already has a parent (odometry's odom -> base_link and the camera's static mounting),
fleetslam publishes ``map -> <root of the camera's tree>`` (usually odom), never a second
parent for the camera.

A tree: each frame has one parent. Dynamic transforms are kept ``keep_s`` behind the newest
and looked up at a stamp by interpolation (linear translation, slerp rotation) between the
two around it; static ones hold at any time. A lookup that cannot be answered raises TfError
with one line: a loop, a missing link, a stamp outside what the buffer holds.
"""

from __future__ import annotations

import bisect
import threading
from dataclasses import dataclass, field

import numpy as np

from fleetslam.transforms import (
    invert,
    make_T,
    matrix_from_quaternion,
    quaternion_from_matrix,
)

_NS = 1_000_000_000
# A frame chain longer than this is taken as a loop (a tree is a few frames deep).
MAX_DEPTH = 100


class TfError(LookupError):
    """A transform the tree cannot give; the text says why, in one line."""


@dataclass
class _Edge:
    parent: str
    static: bool
    stamps: list[int] = field(default_factory=list)  # sorted, ns
    poses: list[np.ndarray] = field(default_factory=list)  # T_parent_child


def _interpolate(A: np.ndarray, B: np.ndarray, f: float) -> np.ndarray:
    qa, qb = quaternion_from_matrix(np.stack([A[:3, :3], B[:3, :3]]))
    if float(np.dot(qa, qb)) < 0:
        qb = -qb
    angle = float(np.arccos(np.clip(np.dot(qa, qb), -1.0, 1.0)))
    if angle < 1e-9:
        q = qa
    else:
        q = (np.sin((1 - f) * angle) * qa + np.sin(f * angle) * qb) / np.sin(angle)
    return make_T(matrix_from_quaternion(q)[0],
                  (1 - f) * A[:3, 3] + f * B[:3, 3])


class TfBuffer:
    def __init__(self, keep_s: float = 10.0) -> None:
        self.keep_ns = int(keep_s * _NS)
        self._edges: dict[str, _Edge] = {}  # child -> its edge to the parent
        self._lock = threading.Lock()

    def add(self, transforms: list[tuple[int, str, str, np.ndarray]], static: bool) -> None:
        """TFMessage contents (stamp ns, parent, child, T_parent_child)."""
        with self._lock:
            for stamp, parent, child, T in transforms:
                edge = self._edges.get(child)
                if edge is None or edge.parent != parent or edge.static != static:
                    edge = self._edges[child] = _Edge(parent, static)  # (re)parented
                if static:
                    edge.stamps, edge.poses = [stamp], [T]
                    continue
                at = bisect.bisect(edge.stamps, stamp)
                if at and edge.stamps[at - 1] == stamp:
                    edge.poses[at - 1] = T
                    continue
                edge.stamps.insert(at, stamp)
                edge.poses.insert(at, T)
                keep_from = bisect.bisect_left(edge.stamps, edge.stamps[-1] - self.keep_ns)
                del edge.stamps[:keep_from], edge.poses[:keep_from]

    def parent(self, frame: str) -> str | None:
        with self._lock:
            edge = self._edges.get(frame)
            return edge.parent if edge is not None else None

    def _chain(self, frame: str) -> list[str]:
        """``frame`` and its ancestors up to the root; TfError on a loop."""
        chain = [frame]
        while (edge := self._edges.get(chain[-1])) is not None:
            if edge.parent in chain or len(chain) > MAX_DEPTH:
                loop = " -> ".join(reversed(chain[chain.index(edge.parent):] + [edge.parent])) \
                    if edge.parent in chain else f"over {MAX_DEPTH} frames"
                raise TfError(f"the TF tree has a loop: {loop}")
            chain.append(edge.parent)
        return chain

    def root(self, frame: str) -> str:
        """The top of ``frame``'s tree (the frame itself if it has no parent)."""
        with self._lock:
            return self._chain(frame)[-1]

    def _at(self, child: str, stamp: int) -> np.ndarray:
        edge = self._edges[child]
        if edge.static:
            return edge.poses[0]
        at = bisect.bisect_left(edge.stamps, stamp)
        if at < len(edge.stamps) and edge.stamps[at] == stamp:
            return edge.poses[at]
        if at == 0 or at == len(edge.stamps):
            have = f"{edge.stamps[0] / _NS:.3f}-{edge.stamps[-1] / _NS:.3f} s"
            raise TfError(f"{edge.parent} -> {child} at {stamp / _NS:.3f} s: the buffer holds "
                          f"{have} (is the robot's clock the camera's?)")
        t0, t1 = edge.stamps[at - 1], edge.stamps[at]
        return _interpolate(edge.poses[at - 1], edge.poses[at], (stamp - t0) / (t1 - t0))

    def lookup(self, target: str, source: str, stamp: int) -> np.ndarray:
        """T_target_source at ``stamp`` ns; TfError saying why not."""
        with self._lock:
            up_source, up_target = self._chain(source), self._chain(target)
            if up_source[-1] != up_target[-1]:
                raise TfError(f"no TF path from {target} to {source}: {source}'s tree ends at "
                              f"{up_source[-1]}, {target}'s at {up_target[-1]}")
            common = next(f for f in up_source if f in up_target)

            def to_common(chain: list[str]) -> np.ndarray:
                T = np.eye(4)
                for child in chain[:chain.index(common)]:
                    T = self._at(child, stamp) @ T
                return T

            return invert(to_common(up_target)) @ to_common(up_source)

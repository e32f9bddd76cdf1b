"""Inter-frame coding of the frame message's descriptors (message kind FRAME_INTER).

Consecutive frames share most of their features, and a descriptor coded alone is at its
bit-entropy bound (~31 of the 34 kB of a frame at point 3). An inter-coded frame names up
to ``MAX_REFERENCES`` earlier frames of the same robot (by seq) that the cloud holds, and
codes each descriptor against the nearest descriptor (Hamming) of those frames, searched
among the keypoints within ``wire.inter_octaves`` pyramid levels of its own (the robot's
choice: the message names rows, however they were found):

    flags     one bit per keypoint: coded against a reference (Hamming < INTER_MAX_HAMMING)
    index     per coded descriptor, its row in the references' descriptors stacked in the
              order the message names them, as byte planes (u8 plane count, then planes)
    whole     the other descriptors, column by column (as an intra frame sends them)
    residual  per coded descriptor, descriptor XOR reference, row by row in one zstd block
              (one entropy table over all rows is smaller than 32 column tables here)
    angles    the keypoints' quantised angles (compact keypoints only): a coded keypoint's
              angle minus its reference's, mod 256; the others as they are

Positions, octaves and per-keypoint depth are still sent as in an intra frame: predicting
them from the reference keypoint did not pay (bench/inter_coding.py's notes).

A reference is usable only once the cloud has it: the robot takes a frame as a reference
after the cloud said it holds it (its "held" reply, sent when the frame is decoded, before
it is tracked; or the frame's feedback) (``InterEncoder.acked``), and only while the
cloud's ring of decoded frames (``ReferenceRing``, its size told in the welcome) must still
hold it. A message whose reference the cloud lacks (a restart, a closed session) is refused
with ``Code.REFERENCE_MISSING``; the robot forgets every reference it had and sends intra
frames until a frame sent after the refusal is acknowledged.
"""

from __future__ import annotations

import functools
import threading
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from fleetslam.config import WireConfig
from fleetslam.pipeline.states import DescribedFrame, FeatureFrame, MatchedFrame, PosedFrame
from fleetslam.wire.binary import Reader, Writer
from fleetslam.wire.envelope import WireError

# Frames one message may code against.
MAX_REFERENCES = 8
# Coded against a reference below this Hamming distance (bits of 256), sent whole otherwise:
# XOR residuals of ~100 differing bits cost about what the descriptor does (measured on
# 7-Scenes: 96 is 1 % smaller than 64, 110 no better).
INTER_MAX_HAMMING = 96
DESCRIPTOR_BYTES = 32
ANGLE_STEPS = 256
# The keypoint table's pyramid level column (as pipeline/front_end.py lays keypoints out).
OCTAVE_COLUMN = 5



class MissingReference(WireError):
    """An inter-coded frame names a reference frame this decoder does not hold."""

    def __init__(self, seq: int, missing: list[int]) -> None:
        super().__init__(f"inter-coded frame seq {seq} refers to frame(s) seq "
                         f"{', '.join(map(str, missing))} that the cloud does not hold "
                         "(send an intra frame)")
        self.seq = seq
        self.missing = missing


@dataclass(frozen=True)
class Reference:
    """What a later frame is coded against: a frame's descriptors and quantised angles,
    exactly as both robot and cloud hold them."""

    descriptors: np.ndarray  # n x 32 uint8
    angles: np.ndarray  # n uint8
    # The keypoints' pyramid levels (n int64), or None when they are not whole levels: the
    # robot's search looks for a descriptor's reference near its own level.
    octaves: np.ndarray | None = None


def quantised_angles(kp: np.ndarray) -> np.ndarray:
    """The keypoint angles as sent (k >= 2): uint8 steps of 360/256 degrees."""
    with np.errstate(invalid="ignore"):
        angle = np.nan_to_num(np.mod(kp[:, 3].astype(np.float64), 360.0))
    return (np.rint(angle * (ANGLE_STEPS / 360)).astype(np.int64) % ANGLE_STEPS).astype(np.uint8)


def features_of(state: object) -> tuple[np.ndarray, np.ndarray] | None:
    """(keypoints, descriptors) of a state that carries descriptors (points 2-5), or None."""
    if isinstance(state, PosedFrame):
        state = state.matched
    if isinstance(state, MatchedFrame):
        state = state.features
    if isinstance(state, (DescribedFrame, FeatureFrame)):
        return state.keypoints, state.descriptors
    return None


def reference_of(state: object) -> Reference | None:
    """The reference a state gives later frames (None: it carries no descriptors). The cloud
    computes it from the decoded state, the robot from its own: the same bits, as decoding
    is exact and the angle is requantised to the step it was sent at."""
    features = features_of(state)
    if features is None:
        return None
    kp, descriptors = features
    return Reference(np.ascontiguousarray(descriptors, np.uint8), quantised_angles(kp),
                     whole_octaves(kp))


def whole_octaves(kp: np.ndarray) -> np.ndarray | None:
    """The keypoints' pyramid levels as integers, or None if any is not a whole level."""
    octave = kp[:, OCTAVE_COLUMN]
    if len(kp) and not (np.isfinite(octave).all() and np.all(octave == np.round(octave))
                        and octave.min() >= 0):
        return None
    return octave.astype(np.int64)


@dataclass
class InterStats:
    """Descriptors of one message, and how many were coded against a reference."""

    descriptors: int = 0
    inter_descriptors: int = 0


# ---------------------------------------------------------------------------------------
# The descriptor block
# ---------------------------------------------------------------------------------------


def _stack(refs: list[Reference]) -> tuple[np.ndarray, np.ndarray]:
    if not refs:
        return np.zeros((0, DESCRIPTOR_BYTES), np.uint8), np.zeros(0, np.uint8)
    return (np.concatenate([r.descriptors for r in refs]),
            np.concatenate([r.angles for r in refs]))


def _stacked_octaves(refs: list[Reference]) -> np.ndarray | None:
    if any(r.octaves is None for r in refs):
        return None
    return np.concatenate([r.octaves for r in refs]) if refs else np.zeros(0, np.int64)


@functools.cache
def _faiss() -> Any:
    """faiss when installed (the cloud extra), else None. Optional on a robot: its exact
    binary index finds the same rows (the lowest row of equal distance, as OpenCV) 3x
    faster (bench/inter_coding.py), but a robot installs only numpy, OpenCV, Zenoh and zstd."""
    try:
        import faiss
    except ImportError:
        return None
    faiss.omp_set_num_threads(1)  # as place_recognition: a robot's few ms are not worth threads
    return faiss


def nearest(descriptors: np.ndarray, stacked: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(row, Hamming distance) of each descriptor's nearest row of ``stacked``, the lowest
    row among equals: faiss's exact binary index (~1.4 ms for 1000 x 1000 on one core) or
    OpenCV's brute-force matcher (~4x slower) without it."""
    n = len(descriptors)
    if not n or not len(stacked):
        return np.zeros(n, np.int64), np.full(n, 256, np.int64)
    faiss = _faiss()
    if faiss is None:
        matches = cv2.BFMatcher(cv2.NORM_HAMMING).match(np.ascontiguousarray(descriptors),
                                                        np.ascontiguousarray(stacked))
        row = np.fromiter((m.trainIdx for m in matches), np.int64, n)
        distance = np.fromiter((m.distance for m in matches), np.float64, n).astype(np.int64)
        return row, distance
    index = faiss.IndexBinaryFlat(8 * DESCRIPTOR_BYTES)
    index.add(np.ascontiguousarray(stacked))
    distance, row = index.search(np.ascontiguousarray(descriptors), 1)
    return row[:, 0].astype(np.int64), distance[:, 0].astype(np.int64)


def nearest_by_octave(descriptors: np.ndarray, octaves: np.ndarray, stacked: np.ndarray,
                      stacked_octaves: np.ndarray, window: int) -> tuple[np.ndarray, np.ndarray]:
    """As :func:`nearest`, each descriptor looking only at rows at most ``window`` pyramid
    levels from its own (distance 256 where none is): the lowest such row among equals,
    whichever matcher, so robots with and without faiss send the same bytes."""
    n = len(descriptors)
    row, distance = np.zeros(n, np.int64), np.full(n, 256, np.int64)
    if not n or not len(stacked):
        return row, distance
    # Both sides grouped by level once (a stable sort: rows keep their order within a
    # level), so a level's queries and its window's rows are slices, not a mask over all
    # 8 references' rows per level (~0.4 ms a frame less).
    q_order = np.argsort(octaves, kind="stable")
    s_order = np.argsort(stacked_octaves, kind="stable")
    q_levels, s_levels = octaves[q_order], stacked_octaves[s_order]
    starts = np.flatnonzero(np.r_[True, q_levels[1:] != q_levels[:-1]])
    ends = np.r_[starts[1:], n]
    lo = np.searchsorted(s_levels, q_levels[starts] - window, "left")
    hi = np.searchsorted(s_levels, q_levels[starts] + window, "right")
    for a, b, first, last in zip(starts.tolist(), ends.tolist(), lo.tolist(), hi.tolist()):
        if first == last:
            continue
        query, allowed = q_order[a:b], s_order[first:last]
        if window:  # rows of several levels: back in row order, so the lowest wins ties
            allowed = np.sort(allowed)
        found, distance[query] = nearest(descriptors[query], stacked[allowed])
        row[query] = allowed[found]
    return row, distance


@functools.cache  # once a process: `fleetslam robot` calls it before its camera, a Robot again
def warm_up() -> None:
    """Pay the search's one-time costs now, not on the first inter-coded frame: importing
    faiss (~30 ms of CPU) and the numpy parts ``np.unique`` imports lazily (~15 ms), which
    made a robot's second frame cost 44-54 ms, past a quarter core's 25 ms a frame
    (bench/robot_cpu.py at 64bc9e0). Searches two made-up descriptors, as a frame would."""
    descriptors, octaves = np.zeros((2, DESCRIPTOR_BYTES), np.uint8), np.zeros(2, np.int64)
    nearest_by_octave(descriptors, octaves, descriptors, octaves, 0)


def put_inter_descriptors(w: Writer, descriptors: np.ndarray, angles: np.ndarray | None,
                          refs: list[Reference], stats: InterStats | None = None,
                          octaves: np.ndarray | None = None,
                          octave_window: int | None = None) -> None:
    """The descriptor block of an inter-coded frame (module docstring); ``angles``: the
    keypoints' quantised angles when the keypoint table left them to this block. With
    ``octaves`` (the keypoints' levels) and ``octave_window``, each descriptor's reference
    is searched only that many levels from its own: the same corner seen at another scale
    is found at a neighbouring level, so the search costs a fraction (``wire.inter_octaves``);
    the decoder reads the rows, however they were chosen."""
    stacked, ref_angles = _stack(refs)
    stacked_octaves = _stacked_octaves(refs)
    if octaves is not None and stacked_octaves is not None and octave_window is not None:
        row, distance = nearest_by_octave(descriptors, octaves, stacked, stacked_octaves,
                                          octave_window)
    else:
        row, distance = nearest(descriptors, stacked)
    coded = distance < INTER_MAX_HAMMING
    rows = row[coded]
    n_bytes = max(1, (max(len(stacked) - 1, 0).bit_length() + 7) // 8)
    w.bits(coded)
    w.pack("B", n_bytes)
    w.planes(rows, n_bytes)
    w.columns(descriptors[~coded])
    w.array(descriptors[coded] ^ stacked[rows], "u1")
    if angles is not None:
        w.array((angles[coded].astype(np.int64) - ref_angles[rows]) % ANGLE_STEPS, "u1")
        w.array(angles[~coded], "u1")
    if stats is not None:
        stats.descriptors += len(descriptors)
        stats.inter_descriptors += int(coded.sum())


def get_inter_descriptors(r: Reader, n: int, refs: list[Reference],
                          with_angles: bool) -> tuple[np.ndarray, np.ndarray | None]:
    """(descriptors, quantised angles or None) of :func:`put_inter_descriptors`."""
    stacked, ref_angles = _stack(refs)
    coded = r.bits(n, "inter-coded descriptor flags")
    m = int(coded.sum())
    (n_bytes,) = r.unpack("B", "reference row bytes")
    if not 1 <= n_bytes <= 4:
        raise WireError(f"reference rows of {n_bytes} bytes")
    rows = r.planes(n_bytes, m, "reference rows")
    if m and rows.max() >= len(stacked):
        raise WireError(f"a descriptor refers to row {rows.max()} of references holding "
                        f"{len(stacked)}")
    descriptors = np.empty((n, DESCRIPTOR_BYTES), np.uint8)
    descriptors[~coded] = r.columns(n - m, DESCRIPTOR_BYTES, "whole descriptors")
    residual = r.array("u1", m * DESCRIPTOR_BYTES, "descriptor residuals")
    descriptors[coded] = residual.reshape(m, DESCRIPTOR_BYTES) ^ stacked[rows]
    angles = None
    if with_angles:
        angles = np.empty(n, np.uint8)
        delta = r.array("u1", m, "angle residuals").astype(np.int64)
        angles[coded] = ((delta + ref_angles[rows]) % ANGLE_STEPS).astype(np.uint8)
        angles[~coded] = r.array("u1", n - m, "angles")
    return descriptors, angles


# ---------------------------------------------------------------------------------------
# The cloud's ring and the robot's choice of references
# ---------------------------------------------------------------------------------------


class ReferenceRing:
    """The newest ``size`` decoded frames of one robot that can serve as references, by seq
    (a cloud session's; only its frame thread uses it)."""

    def __init__(self, size: int) -> None:
        self.size = max(0, int(size))
        self._frames: OrderedDict[int, Reference] = OrderedDict()

    def put(self, seq: int, reference: Reference | None) -> None:
        if reference is None or not self.size:
            return
        self._frames[seq] = reference
        self._frames.move_to_end(seq)
        while len(self._frames) > self.size:
            self._frames.popitem(last=False)

    def get(self, seq: int) -> Reference | None:
        return self._frames.get(seq)

    def __contains__(self, seq: object) -> bool:
        return seq in self._frames

    def __len__(self) -> int:
        return len(self._frames)

    def nbytes(self) -> int:
        """Bytes the references hold (the cloud counts them in a session's budget)."""
        return sum(r.descriptors.nbytes + r.angles.nbytes for r in self._frames.values())

    def clear(self) -> None:
        self._frames.clear()


@dataclass
class InterCounts:
    """What the robot's report says about its coding (RobotReport.inter_coding)."""

    intra_frames: int = 0
    inter_frames: int = 0
    descriptors: int = 0
    inter_descriptors: int = 0
    refusals: int = 0  # the cloud lacked a reference (REFERENCE_MISSING)
    references_per_frame: list[int] = field(default_factory=list)

    def summary(self) -> dict[str, float | int]:
        frames = self.intra_frames + self.inter_frames
        return {
            "intra_frames": self.intra_frames, "inter_frames": self.inter_frames,
            "intra_share": self.intra_frames / frames if frames else 0.0,
            "inter_descriptor_share": self.inter_descriptors / self.descriptors
            if self.descriptors else 0.0,
            "refusals": self.refusals,
            "mean_references": float(np.mean(self.references_per_frame))
            if self.references_per_frame else 0.0,
        }


class InterEncoder:
    """The robot's side: which frames the cloud holds, and which to code the next one
    against. Feedback and refusals arrive on Zenoh threads while the main thread encodes.

    ``cloud_ring``: how many frames the cloud's ring holds (its welcome says; 0 = a cloud
    that does not decode inter-coded frames). A frame acknowledged as seq s is still in that
    ring for a frame seq t if t - s <= cloud_ring: the cloud accepted at most t - s - 1 frames
    after s."""

    def __init__(self, config: WireConfig, cloud_ring: int = 0) -> None:
        self.enabled = bool(config.inter_frame)
        self.max_refs = max(0, min(int(config.inter_references), MAX_REFERENCES))
        self.intra_every = max(1, int(config.intra_every))
        self.counts = InterCounts()
        self._lock = threading.Lock()
        self._sent: OrderedDict[int, Reference] = OrderedDict()
        self._acked: set[int] = set()
        self._epoch = 0  # acks of frames sent before this seq are not trusted
        self._last_intra: int | None = None
        self.set_cloud_ring(cloud_ring)

    def set_cloud_ring(self, size: int) -> None:
        with self._lock:
            self.window = max(0, min(int(size), int(1 << 16)))

    def restart(self, next_seq: int) -> None:
        """A new (or resumed) session with the cloud: nothing it held before counts."""
        with self._lock:
            self._acked.clear()
            self._sent.clear()
            self._epoch = next_seq
            self._last_intra = None

    def choose(self, seq: int) -> list[tuple[int, Reference]]:
        """The references for frame ``seq``, newest first; [] for an intra frame."""
        with self._lock:
            if not (self.enabled and self.max_refs and self.window):
                return []
            if self._last_intra is None or seq - self._last_intra >= self.intra_every:
                return []
            usable = sorted((s for s in self._acked
                             if s >= self._epoch and 0 < seq - s <= self.window
                             and s in self._sent), reverse=True)
            return [(s, self._sent[s]) for s in usable[:self.max_refs]]

    def sent(self, seq: int, reference: Reference | None, refs: int) -> None:
        """Frame ``seq`` went out, coded against ``refs`` frames (0: intra)."""
        with self._lock:
            if refs:
                self.counts.inter_frames += 1
            else:
                self.counts.intra_frames += 1
                self._last_intra = seq
            self.counts.references_per_frame.append(refs)
            if reference is not None:
                self._sent[seq] = reference
            while self._sent and next(iter(self._sent)) < seq - max(self.window, 1):
                old, _ = self._sent.popitem(last=False)
                self._acked.discard(old)

    def acked(self, seq: int) -> None:
        """The cloud decoded frame ``seq`` (its "held" reply or the frame's feedback)."""
        with self._lock:
            if seq in self._sent and seq >= self._epoch:
                self._acked.add(seq)

    def refused(self, next_seq: int) -> None:
        """The cloud lacked a reference: trust no acknowledgement of a frame sent before
        ``next_seq`` (the cloud may have lost them all), and send intra until a frame sent
        from then on is acknowledged."""
        with self._lock:
            self.counts.refusals += 1
            self._acked.clear()
            self._epoch = max(self._epoch, next_seq)

    def record(self, stats: InterStats) -> None:
        with self._lock:
            self.counts.descriptors += stats.descriptors
            self.counts.inter_descriptors += stats.inter_descriptors

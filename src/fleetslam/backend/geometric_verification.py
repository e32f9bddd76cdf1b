"""Robust rigid alignment of 3D-3D matches: the geometric check of a place-recognition
candidate (depth-backed keypoints of one keyframe against landmarks of another place).

RANSAC over minimal samples of three matches, all hypotheses at once: the rotations come
from one batched SVD (Kabsch), the inliers of every hypothesis from one broadcast distance
test. The best hypothesis is refitted on its inliers until the inlier set stops changing.
A match is an inlier within max(inlier_m, depth_ratio * depth): depth noise of a
structured-light or time-of-flight camera grows with distance.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class RigidMatch:
    T_target_source: np.ndarray  # 4 x 4
    inliers: np.ndarray  # bool per match
    rmse_m: float

    @property
    def n_inliers(self) -> int:
        return int(self.inliers.sum())


def kabsch(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Least-squares rigid T (4 x 4) with target ~ R source + t; batched over a leading
    axis when the inputs are (B, n, 3)."""
    batched = source.ndim == 3
    src = source if batched else source[None]
    dst = target if batched else target[None]
    mu_s, mu_d = src.mean(axis=1), dst.mean(axis=1)
    H = np.einsum("bni,bnj->bij", src - mu_s[:, None], dst - mu_d[:, None])
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.einsum("bij,bjk->bik", U, Vt)))
    D = np.ones((len(src), 3))
    D[:, 2] = d
    R = np.einsum("bji,bj,bkj->bik", Vt, D, U)  # V diag(D) U^T
    T = np.tile(np.eye(4), (len(src), 1, 1))
    T[:, :3, :3] = R
    T[:, :3, 3] = mu_d - np.einsum("bij,bj->bi", R, mu_s)
    return T if batched else T[0]


def sample_triples(rng: np.random.Generator, n: int, count: int) -> np.ndarray:
    """``count`` x 3 indices: the rows ``rng.choice(n, 3, replace=False)`` gives when called
    ``count`` times, and ``rng`` left as those calls leave it, in one vectorised pass instead
    of ``count`` calls of ~12 us of overhead each. numpy draws each triple from five 32-bit
    words of its PCG64 stream (low half of a 64-bit draw first): Floyd's sampling, a bounded
    draw (Lemire's multiply-shift) in [0, j] for j = n-3, n-2, n-1, an index already taken
    replaced by j; then a Fisher-Yates shuffle with bounded draws in [0, 2] and [0, 1]. A
    bounded draw rejects a word (and takes another) with probability below (j + 1) / 2^32;
    then, or for another bit generator, the triples come from ``rng.choice`` itself.
    tests/test_geometric_verification.py checks all of it against ``rng.choice``."""
    def by_choice() -> np.ndarray:
        return np.array([rng.choice(n, 3, replace=False) for _ in range(count)],
                        np.int64).reshape(count, 3)

    bits = rng.bit_generator
    start = bits.state
    if start.get("bit_generator") != "PCG64" or not 4 <= n <= 0xFFFFFFFF or count == 0:
        return by_choice()
    # The 32-bit words in the order numpy takes them: a half left over from before first.
    pending = [start["uinteger"]] if start["has_uint32"] else []
    words_needed = 5 * count
    n_raw = (words_needed - len(pending) + 1) // 2
    raw = bits.random_raw(n_raw)
    words = np.concatenate([np.array(pending, np.uint64),
                            raw.view(np.uint32).astype(np.uint64)])[:words_needed]
    words = words.reshape(count, 5)
    bound = np.array([n - 3, n - 2, n - 1, 2, 1], np.uint64)
    m = words * (bound + np.uint64(1))
    low = m & np.uint64(0xFFFFFFFF)
    threshold = (np.uint64(0xFFFFFFFF) - bound) % (bound + np.uint64(1))
    if (low < threshold).any():  # a rejected word: numpy drew another (rare)
        bits.state = start
        return by_choice()
    draw = (m >> np.uint64(32)).astype(np.int64)
    a = draw[:, 0]
    b = np.where(draw[:, 1] == a, n - 2, draw[:, 1])
    c = np.where((draw[:, 2] == a) | (draw[:, 2] == b), n - 1, draw[:, 2])
    out = np.stack([a, b, c], axis=1)
    rows = np.arange(count)
    for i, k in ((2, 3), (1, 4)):  # swap position i with the drawn one
        j = draw[:, k]
        taken = out[rows, j]
        out[rows, j] = out[:, i]
        out[:, i] = taken
    # The generator as numpy's calls leave it: the raw draws whose words were used, and a
    # 64-bit draw's high half still unused if the words ended on a low half.
    used_words = words_needed - len(pending)
    bits.state = start
    state = bits.state
    if used_words > 0:
        used_raw = (used_words + 1) // 2
        bits.random_raw(used_raw)
        state = bits.state
        if used_words % 2:
            state["has_uint32"], state["uinteger"] = 1, int(raw[used_raw - 1] >> np.uint64(32))
        else:
            state["has_uint32"], state["uinteger"] = 0, int(raw[used_raw - 1] >> np.uint64(32))
    else:
        state["has_uint32"] = 0
    bits.state = state
    return out


def ransac_rigid(source: np.ndarray, target: np.ndarray, threshold_m: np.ndarray,
                 iterations: int, min_inliers: int, rng: np.random.Generator,
                 refits: int = 5) -> RigidMatch | None:
    """Rigid T_target_source from matched points (n x 3 each) with per-match inlier
    thresholds; None when fewer than ``min_inliers`` agree."""
    n = len(source)
    if n < max(3, min_inliers):
        return None
    samples = sample_triples(rng, n, iterations)
    src, dst = source[samples], target[samples]
    # Degenerate samples (nearly collinear points) give arbitrary rotations: skip them.
    area = np.linalg.norm(np.cross(src[:, 1] - src[:, 0], src[:, 2] - src[:, 0]), axis=1)
    good = area > 1e-4
    if not good.any():
        return None
    T = kabsch(src[good], dst[good])
    # Every hypothesis applied to every match, one (hypotheses x matches) array per
    # coordinate: ~20x faster than np.einsum("bij,nj->bni") and the same sums in the same
    # order as numpy's einsum adds them (terms 0 and 2, then 1), then the distance to the
    # target as np.linalg.norm adds its squares.
    R, t = T[:, :3, :3], T[:, :3, 3]
    s0, s1, s2 = (np.ascontiguousarray(source[:, c]) for c in range(3))
    for i in range(3):
        moved = (R[:, i, 0, None] * s0 + R[:, i, 2, None] * s2) + R[:, i, 1, None] * s1
        d = (moved + t[:, i, None]) - target[:, i]
        sq = d * d if i == 0 else sq + d * d
    err = np.sqrt(sq)
    counts = (err <= threshold_m[None]).sum(axis=1)
    best = int(np.argmax(counts))
    inliers = err[best] <= threshold_m
    if inliers.sum() < min_inliers:
        return None
    T_best = T[best]
    for _ in range(refits):
        T_best = kabsch(source[inliers], target[inliers])
        err1 = np.linalg.norm(source @ T_best[:3, :3].T + T_best[:3, 3] - target, axis=1)
        new = err1 <= threshold_m
        if new.sum() < 3 or np.array_equal(new, inliers):
            inliers = new if new.sum() >= 3 else inliers
            break
        inliers = new
    if inliers.sum() < min_inliers:
        return None
    err1 = np.linalg.norm(source @ T_best[:3, :3].T + T_best[:3, 3] - target, axis=1)
    return RigidMatch(T_best, inliers, float(np.sqrt(np.mean(err1[inliers] ** 2))))

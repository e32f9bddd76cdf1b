"""Feature matching: descriptor matching against landmarks, by descriptor alone or guided
by a predicted pose (candidates near their projection, at a compatible pyramid level)."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
from scipy.spatial import cKDTree

from fleetslam.backend.state import BackEndState
from fleetslam.pipeline.states import FeatureFrame


def hamming_rows(a: np.ndarray, rows_a: np.ndarray, b: np.ndarray, rows_b: np.ndarray
                 ) -> np.ndarray:
    """Hamming distance of descriptor a[rows_a[k]] to b[rows_b[k]] for every k (uint16).
    Rows are gathered and compared as 4 uint64 words, 8x fewer elements than bytes, and the
    four counts added column by column (a reduction over an axis of 4 costs more)."""
    a64 = np.ascontiguousarray(a, dtype=np.uint8).view(np.uint64)
    b64 = np.ascontiguousarray(b, dtype=np.uint8).view(np.uint64)
    x = a64[rows_a]
    x ^= b64[rows_b]
    c = np.bitwise_count(x)
    out = c[:, 0].astype(np.uint16)
    out += c[:, 1]
    out += c[:, 2]
    out += c[:, 3]
    return out


def descriptor_match(query: np.ndarray, train: np.ndarray, train_ids: np.ndarray,
                     max_hamming: int, ratio: float, mask: np.ndarray | None = None
                     ) -> np.ndarray:
    """Best descriptor match per query (Hamming, Lowe ratio, optional mask), one query per
    train item; train ids per query, -1 if none."""
    ids = np.full(len(query), -1, np.int64)
    if len(train) < 2 or len(query) == 0:
        return ids
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
    pairs = matcher.knnMatch(query, train, k=2, mask=mask) if mask is not None else \
        matcher.knnMatch(query, train, k=2)
    q, t, dist = [], [], []
    for p in pairs:
        if not p:
            continue
        best = p[0]
        if best.distance > max_hamming:
            continue
        if len(p) > 1 and best.distance > ratio * p[1].distance:
            continue
        q.append(best.queryIdx)
        t.append(best.trainIdx)
        dist.append(best.distance)
    if not q:
        return ids
    q_arr, t_arr, d_arr = np.array(q), np.array(t), np.array(dist)
    # One keypoint per landmark: the closest descriptor wins.
    order = np.lexsort((d_arr, t_arr))
    first = np.ones(len(order), bool)
    first[1:] = t_arr[order][1:] != t_arr[order][:-1]
    keep = order[first]
    ids[q_arr[keep]] = train_ids[t_arr[keep]]
    return ids


def guided_match(state: FeatureFrame, descriptors: np.ndarray, candidates: np.ndarray,
                 projected: np.ndarray, predicted_level: np.ndarray, radius_px: float,
                 scale_factor: float, max_hamming: int, ratio: float) -> np.ndarray:
    """Match each keypoint to the candidate landmarks projected within a radius of it
    (scaled by the keypoint's octave) and predicted at its pyramid level +-1. Landmark id
    per keypoint, -1 if none; one keypoint per landmark."""
    n = len(state.keypoints)
    ids = np.full(n, -1, np.int64)
    if len(candidates) == 0 or n == 0:
        return ids
    # One radius search per pyramid level: the search radius grows with the keypoint's scale.
    octave = state.keypoints[:, 5].astype(int)
    lm_parts, kp_parts = [], []
    for level in np.unique(octave):
        members = np.flatnonzero(octave == level)
        near = np.flatnonzero(np.abs(predicted_level - level) <= 1)
        if len(near) == 0:
            continue
        pairs = cKDTree(projected[near]).sparse_distance_matrix(
            cKDTree(state.uv[members]), radius_px * scale_factor**level, output_type="ndarray")
        lm_parts.append(near[pairs["i"]])
        kp_parts.append(members[pairs["j"]])
    if not lm_parts:
        return ids
    lm, kp = np.concatenate(lm_parts), np.concatenate(kp_parts)
    if len(lm) == 0:
        return ids
    ham = hamming_rows(state.descriptors, kp, descriptors, candidates[lm])
    # Best and second-best landmark per keypoint.
    # By keypoint, then distance (ties in input order): one stable sort of a combined key
    # is several times faster than lexsort on this many pairs.
    order = np.argsort(kp * 257 + ham.astype(np.int64), kind="stable")
    kp, lm, ham = kp[order], lm[order], ham[order]
    first = np.ones(len(kp), bool)
    first[1:] = kp[1:] != kp[:-1]
    best = np.flatnonzero(first)
    second = best + 1
    has_second = (second < len(kp)) & ~np.append(first, True)[np.minimum(second, len(kp))]
    second_ham = np.full(len(best), np.inf)
    second_ham[has_second] = ham[second[has_second]]
    good = (ham[best] <= max_hamming) & (ham[best] < ratio * second_ham)
    best = best[good]
    # One keypoint per landmark: the closest descriptor wins.
    order = np.lexsort((ham[best], lm[best]))
    best = best[order]
    unique = np.ones(len(best), bool)
    unique[1:] = lm[best][1:] != lm[best][:-1]
    best = best[unique]
    ids[kp[best]] = candidates[lm[best]]
    return ids


def in_scale_range(session: BackEndState, ids: np.ndarray, P: np.ndarray) -> np.ndarray:
    """Landmarks ``ids`` at camera-frame points ``P`` whose distance lies within their
    scale-invariance range, ORB-SLAM's [0.8 d_min, 1.2 d_max] with d_max = d * s^octave,
    d_min = d_max / s^(levels - 1) (d, octave: of the landmark's reference view)."""
    orb, lmap = session.config.orb, session.map
    dist = np.linalg.norm(P, axis=1)
    d_max = lmap.distance[ids] * orb.scale_factor ** lmap.octave[ids]
    d_min = d_max / orb.scale_factor ** (orb.n_levels - 1)
    return (dist >= 0.8 * d_min) & (dist <= 1.2 * d_max)


def match_free_keypoints(session: BackEndState, f: FeatureFrame, T_world_camera: np.ndarray,
                         matched_ids: np.ndarray, radius_px: float, max_hamming: int,
                         ratio: float, scale_check: bool) -> np.ndarray:
    """``matched_ids`` plus matches of its free keypoints (-1) to the live landmarks not yet
    matched, projected from ``T_world_camera`` and searched within ``radius_px``;
    ``scale_check`` also requires each landmark's scale-invariance distance range."""
    cfg, orb, lmap = session.config.tracking, session.config.orb, session.map
    free_kp = np.flatnonzero(matched_ids < 0)
    cand, proj, P = lmap.in_view(session.camera, T_world_camera, cfg.min_depth_m,
                                 cfg.max_depth_m, ids=session.tracking_landmarks())
    unmatched = np.ones(lmap.n_landmarks, bool)
    unmatched[matched_ids[matched_ids >= 0]] = False
    keep = unmatched[cand]
    if scale_check:
        keep[keep] = in_scale_range(session, cand[keep], P[keep])
    cand, proj, P = cand[keep], proj[keep], P[keep]
    ids = matched_ids.copy()
    if len(free_kp) and len(cand):
        level = lmap.predicted_octave(cand, np.linalg.norm(P, axis=1), orb.scale_factor,
                                      orb.n_levels)
        sub = replace(f, keypoints=f.keypoints[free_kp], descriptors=f.descriptors[free_kp],
                      depth=f.depth[free_kp], uv=f.uv[free_kp])
        ids[free_kp] = guided_match(sub, lmap.descriptors, cand, proj, level, radius_px,
                                    orb.scale_factor, max_hamming, ratio)
    return ids

"""Keyframe culling (ORB-SLAM's KeyFrameCulling) and the keyframe test's motion reference:
what keeps a place revisited pass after pass from adding a pass's worth of keyframes, and
of local BA, each time."""

from __future__ import annotations

import numpy as np

from fleetslam.backend.local_map import LocalMap
from fleetslam.camera import Camera
from fleetslam.pipeline.states import FeatureFrame
from conftest import SEVEN_SCENES, require

CAMERA = Camera(525.0, 525.0, 319.5, 239.5, 640, 480)
N_LEVELS = 8
CLOSE_M = 3.2


def observed_map(observers: dict[int, np.ndarray], n_keyframes: int, depth: float = 1.5,
                 octave: dict[int, int] | None = None) -> LocalMap:
    """A map of ``n_keyframes`` keyframes at the origin in which keyframe k observes the
    landmarks ``observers[k]`` (ids into one set of 100), with ``depth`` and at pyramid level
    ``octave[k]`` (0 if not given)."""
    rng = np.random.default_rng(0)
    lmap = LocalMap()
    n = 100
    xyz = np.column_stack([rng.uniform(-0.5, 0.5, n), rng.uniform(-0.5, 0.5, n),
                           np.full(n, depth)])
    map_id = np.full(n, -1)
    for k in range(n_keyframes):
        seen = observers.get(k, np.zeros(0, np.int64))
        uv = CAMERA.project(xyz[seen])
        keypoints = np.zeros((len(seen), 7), np.float32)
        keypoints[:, :2] = uv
        keypoints[:, 5] = (octave or {}).get(k, 0)
        features = FeatureFrame(k, float(k), keypoints,
                                rng.integers(0, 256, (len(seen), 32), dtype=np.uint8),
                                np.full(len(seen), depth, np.float32), uv)
        start = lmap.n_landmarks
        matched = map_id[seen]
        lmap.add_keyframe(CAMERA, features, np.eye(4), matched)
        created = seen[matched < 0]
        map_id[created] = np.arange(start, start + len(created))
    return lmap


def redundant(lmap: LocalMap, candidates) -> list[int]:
    return lmap.redundant_keyframes(np.asarray(candidates, np.int64), CLOSE_M, N_LEVELS,
                                    3, 0.9).tolist()


def test_a_keyframe_whose_landmarks_three_others_see_is_redundant():
    everything = np.arange(100)
    lmap = observed_map({k: everything for k in range(5)}, 5)
    assert redundant(lmap, [1, 2, 3, 4]) == [1, 2, 3, 4]


def test_two_other_observers_are_not_enough():
    everything = np.arange(100)
    lmap = observed_map({k: everything for k in range(3)}, 3)
    assert redundant(lmap, [1, 2]) == []


def test_a_keyframe_with_a_tenth_of_its_landmarks_its_own_stays():
    shared, own = np.arange(80), np.arange(80, 100)
    lmap = observed_map({0: shared, 1: shared, 2: shared, 3: np.concatenate([shared, own])}, 4)
    # Keyframe 3 alone sees 20 % of its landmarks; the others see only shared ones.
    assert redundant(lmap, [1, 2, 3]) == [1, 2]


def test_observers_at_a_coarser_scale_do_not_count():
    everything = np.arange(100)
    # Keyframe 4 sees the landmarks at level 0; the others at level 3 (coarser than 0 + 1).
    lmap = observed_map({k: everything for k in range(5)}, 5, octave={0: 3, 1: 3, 2: 3, 3: 3})
    assert 4 not in redundant(lmap, [4])
    lmap = observed_map({k: everything for k in range(5)}, 5, octave={0: 1, 1: 1, 2: 1, 3: 1})
    assert redundant(lmap, [4]) == [4]


def test_far_landmarks_do_not_make_a_keyframe_redundant():
    everything = np.arange(100)
    lmap = observed_map({k: everything for k in range(5)}, 5, depth=CLOSE_M + 0.5)
    assert redundant(lmap, [1, 2, 3, 4]) == []


def test_a_culled_keyframe_keeps_its_pose_and_its_landmarks_live():
    everything = np.arange(100)
    lmap = observed_map({k: everything for k in range(5)}, 5)
    rows_before = lmap.n_observations
    assert lmap.drop_keyframe_observations(np.array([2])) == 100
    assert lmap.n_observations == rows_before - 100
    assert not (lmap.obs_keyframe == 2).any()
    assert lmap.alive.all()
    assert len(lmap.keyframes) == 5 and lmap.keyframes[2].T_world_camera is not None


def test_a_third_pass_over_a_mapped_place_adds_few_keyframes():
    """Real frames: redkitchen 0-199, back 198-1, and 0-199 again. The third pass, over a
    place mapped twice, makes a small fraction of the keyframes the first one did (the
    keyframe test measures motion from the keyframe the frame shares most landmarks with
    too, not only from the newest), and tracking loses no frame."""
    from fleetslam.config import Config
    from fleetslam.datasets.recording import open_source
    from fleetslam.system import RobotTracker

    sequence = open_source(f"{require(SEVEN_SCENES)}:0-199,198-1,0-199")
    tracker = RobotTracker("r0", "redkitchen", sequence, Config())
    counts = []
    for i in range(len(sequence)):
        tracker.step(i)
        if i in (199, 397):
            counts.append(len(tracker.state.map.keyframes))
    first, third = counts[0], len(tracker.state.map.keyframes) - counts[1]
    run = tracker.finish()
    assert run.lost_frames == 0
    # Measured: 22 keyframes on the first pass, 2 on the third (12 from the newest).
    assert first >= 10 and third <= first // 4, (first, third)

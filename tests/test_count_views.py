"""ORB-SLAM's visible/found counters, counted per frame over the newest landmarks only (the
ones their culling reads), not the whole map: the same culling, the same map and poses as
with every landmark in view counted, and old landmarks left alone."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import TUM_RPY, require

from fleetslam.backend import tracking
from fleetslam.backend.matching import in_scale_range
from fleetslam.config import Config
from fleetslam.datasets.tum import RgbdSequence
from fleetslam.system import RobotTracker

FRAMES = 100


def count_every_landmark(backend, state) -> None:
    """The counters as before: every live landmark of the map tested for visibility."""
    cfg, lmap = backend.config.tracking, backend.map
    ids, _, P = lmap.in_view(backend.camera, state.T_world_camera, cfg.min_depth_m,
                             cfg.max_depth_m)
    ids = ids[in_scale_range(backend, ids, P)]
    found = state.matched.landmark_ids[state.inliers]
    lmap.count_views(ids, found[found >= 0])


def track(folder, monkeypatch, counter=None):
    with monkeypatch.context() as patch:
        if counter is not None:
            patch.setattr(tracking, "count_views", counter)
        sequence = RgbdSequence(folder)
        tracker = RobotTracker("r", str(folder), sequence, Config(), None)
        for i in range(FRAMES):
            tracker.step(i)
        return tracker.state


@pytest.mark.realdata
def test_counting_the_newest_landmarks_culls_and_tracks_as_counting_all(monkeypatch):
    folder = require(TUM_RPY)
    every = track(folder, monkeypatch, count_every_landmark)
    newest = track(folder, monkeypatch)
    assert every.culled_landmarks > 0  # culling by the counters did happen
    a, b = every.map, newest.map
    assert len(a.keyframes) == len(b.keyframes) > 5
    np.testing.assert_array_equal(a.keyframe_poses(), b.keyframe_poses())
    np.testing.assert_array_equal(a.alive, b.alive)
    np.testing.assert_array_equal(a.xyz, b.xyz)
    np.testing.assert_array_equal(a.n_found, b.n_found)
    assert every.culled_landmarks == newest.culled_landmarks
    # The landmarks still on probation were counted alike; older ones in view were not
    # counted again (their counters are no longer read).
    probation = b.created_since(b.keyframes[-1].id + 1
                                - Config().tracking.cull_probation_keyframes)
    np.testing.assert_array_equal(a.n_visible[probation], b.n_visible[probation])
    assert (b.n_visible <= a.n_visible).all() and (b.n_visible < a.n_visible).any()


def test_created_since_is_the_tail_of_the_ids():
    from fleetslam.backend.local_map import LocalMap

    lmap = LocalMap()
    lmap.first_keyframe = np.array([0, 0, 1, 1, 1, 3, 4], np.int64)
    lmap.xyz = np.zeros((7, 3))
    assert lmap.created_since(1).tolist() == [2, 3, 4, 5, 6]
    assert lmap.created_since(2).tolist() == [5, 6]
    assert lmap.created_since(-2).tolist() == list(range(7))
    assert lmap.created_since(5).tolist() == []

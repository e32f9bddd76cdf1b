"""Dense refinement of a constraint on real depth: a feature-like start a few degrees off
ends near ground truth, a wrong start is refused, and where the depth cannot see (a plane)
the feature estimate keeps its say."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from conftest import SEVEN_SCENES, require
from fleetslam.config import Config
from fleetslam.datasets.recording import open_source
from fleetslam.mapping.dense_map import keyframe_local_cloud
from fleetslam.merging.dense_constraint import feature_information, refine
from fleetslam.registration.metrics import transform_error
from fleetslam.transforms import invert


def _off(T: np.ndarray, rotation_deg: float, translation_m: float) -> np.ndarray:
    """T moved by a fixed rotation about a tilted axis and a translation (right side)."""
    axis = np.array([0.3, 1.0, 0.2]) / np.linalg.norm([0.3, 1.0, 0.2])
    move = np.r_[axis * np.deg2rad(rotation_deg), np.array([1.0, -0.5, 0.3])
                 / np.linalg.norm([1.0, -0.5, 0.3]) * translation_m]
    return T @ gtsam.Pose3.Expmap(move).matrix()


@pytest.fixture(scope="module")
def kitchen_pair():
    """Redkitchen frames 241 and 589: one place seen 350 frames apart (a shared-pair
    constraint of the two-robot run), as depth clouds, and their true relative pose."""
    sequence = open_source(str(require(SEVEN_SCENES)))
    config = Config()

    def cloud(i: int) -> np.ndarray:
        frame = sequence[i]
        return keyframe_local_cloud(sequence.camera, frame.rgb, frame.depth_m, config.map)[0]

    true = invert(sequence.gt_poses[241]) @ sequence.gt_poses[589]
    return cloud(241), cloud(589), true


@pytest.mark.realdata
def test_a_feature_like_start_ends_within_two_degrees_of_ground_truth(kitchen_pair):
    place, query, true = kitchen_pair
    start = _off(true, 4.0, 0.07)  # what the feature constraint of this pair measured
    result = refine(place, query, start, Config().merge)
    assert result.accepted, result.reason
    err = transform_error(result.T_place_query, true)
    assert err.rotation_deg < 2.0 and err.translation_m < 0.05, err
    assert result.overlap > 0.3 and 0 < result.iterations


@pytest.mark.realdata
def test_a_wrong_start_is_refused_not_refined(kitchen_pair):
    place, query, true = kitchen_pair
    result = refine(place, query, _off(true, 15.0, 0.05), Config().merge)
    assert not result.accepted and result.T_place_query is None
    assert result.reason  # says why (not converged, too little overlap, or moved too far)


def test_too_few_points_are_refused():
    points = np.random.default_rng(0).uniform(-1, 1, (100, 3))
    result = refine(points, points, np.eye(4), Config().merge)
    assert not result.accepted and "too few depth points" in result.reason


def test_along_a_plane_the_feature_estimate_keeps_its_say():
    """Two views of one textureless floor: GICP fixes the height and the tilt, but cannot
    see a slide along the floor; there the fused edge keeps the feature estimate, with the
    feature's weight, instead of wherever GICP stopped."""
    rng = np.random.default_rng(1)
    floor = np.c_[rng.uniform(-1.5, 1.5, (40000, 2)), rng.normal(0, 0.001, 40000)]
    cfg = Config().merge
    # The feature estimate: right in the plane's slide (x) by 3 cm, wrong in height by 2 cm.
    start = np.eye(4)
    start[:3, 3] = [0.03, 0.0, 0.02]
    result = refine(floor, floor, start, cfg)
    assert result.accepted, result.reason
    assert result.T_place_query is not None and result.information is not None
    x, y, z = result.T_place_query[:3, 3]
    assert abs(z) < 0.003  # the height: from the depth
    assert x == pytest.approx(0.03, abs=0.005)  # the slide: the feature estimate's
    feature = feature_information(cfg)
    # Along the slide the information is about the feature's (GICP adds little: its
    # normalised covariances keep a plane's tangent weight 1/1000 of its normal's), across
    # it far more.
    assert feature[3, 3] <= result.information[3, 3] < 1.3 * feature[3, 3]
    assert result.information[5, 5] > 20 * feature[5, 5]

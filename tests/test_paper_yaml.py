"""The paper's YAML message: OpenCV writes it, OpenCV reads it back, values survive."""

from __future__ import annotations

import numpy as np
import pytest

from fleetslam.pipeline.states import FeatureFrame
from fleetslam.wire.paper_yaml import paper_yaml_bytes, read_paper_yaml, write_paper_yaml


def features(n: int = 1000) -> FeatureFrame:
    rng = np.random.default_rng(0)
    kp = np.zeros((n, 7), np.float32)
    kp[:, 0], kp[:, 1] = rng.uniform(0, 640, n), rng.uniform(0, 480, n)
    kp[:, 2] = 31 * 1.2 ** rng.integers(0, 8, n)
    kp[:, 3], kp[:, 4] = rng.uniform(0, 360, n), rng.uniform(0, 0.01, n)
    kp[:, 5], kp[:, 6] = rng.integers(0, 8, n), -1
    depth = rng.uniform(0.5, 4.0, n).astype(np.float32)
    desc = rng.integers(0, 256, (n, 32), dtype=np.uint8)
    return FeatureFrame(7, 1305031229.528748, kp, desc, depth, kp[:, :2].astype(np.float64))


def test_round_trip_through_opencv(tmp_path):
    f = features()
    path = tmp_path / "frame.yml"
    write_paper_yaml(path, f)
    assert path.read_text().startswith("%YAML:1.0")
    msg = read_paper_yaml(path)
    np.testing.assert_allclose(msg.keypoints, f.keypoints, rtol=1e-6)
    np.testing.assert_allclose(msg.depth, f.depth, rtol=1e-6)
    np.testing.assert_array_equal(msg.descriptors, f.descriptors)
    assert msg.time == pytest.approx(f.timestamp, abs=1e-6)


def test_size_is_of_the_papers_order():
    # The paper reports ~290 kB per frame for this message at 1000 features.
    size = len(paper_yaml_bytes(features(1000)))
    assert 100_000 < size < 400_000


def test_bad_files_are_named(tmp_path):
    with pytest.raises(ValueError, match="no such message file"):
        read_paper_yaml(tmp_path / "none.yml")
    bad = tmp_path / "bad.yml"
    bad.write_text("%YAML:1.0\nTime: 1.0\n")
    with pytest.raises(ValueError, match="bad.yml: message lacks KeyPoint, Depth, Descriptor"):
        read_paper_yaml(bad)

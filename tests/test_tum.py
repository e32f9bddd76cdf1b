"""The TUM RGB-D reader: association, camera choice, ground truth, clear errors."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from conftest import SEVEN_SCENES, TUM_RPY, require
from fleetslam.datasets.ranges import parse_robot_spec
from fleetslam.datasets.tum import RgbdSequence, associate


DEPTH_RAW = 5000  # 1 m with the TUM cameras' depth scale


def frame_rgb(i: int) -> np.ndarray:
    """The colour image ``write_tum_folder`` writes for its i-th rgb stamp: one colour, its
    channels distinct (a swap of red and blue shows), its blue the frame's number."""
    return np.full((48, 64, 3), (200, 100, 10 + i), np.uint8)


def write_tum_folder(root: Path, rgb_times, depth_times, gt: bool = True) -> Path:
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    with open(root / "rgb.txt", "w") as f:
        f.write("# color images\n# timestamp filename\n")
        for i, t in enumerate(rgb_times):
            name = f"rgb/{t:.6f}.png"
            cv2.imwrite(str(root / name), cv2.cvtColor(frame_rgb(i), cv2.COLOR_RGB2BGR))
            f.write(f"{t:.6f} {name}\n")
    with open(root / "depth.txt", "w") as f:
        for t in depth_times:
            name = f"depth/{t:.6f}.png"
            cv2.imwrite(str(root / name), np.full((48, 64), DEPTH_RAW, np.uint16))
            f.write(f"{t:.6f} {name}\n")
    if gt:
        with open(root / "groundtruth.txt", "w") as f:
            for k in range(0, 41):
                t = k * 0.05
                f.write(f"{t:.4f} {t:.4f} 0 0 0 0 0 1\n")
    return root


def test_associate_pairs_nearest_within_20ms_each_stamp_once():
    rgb = np.array([0.0, 0.033, 0.066, 0.5])
    depth = np.array([0.005, 0.030, 0.041, 0.2])
    pairs = associate(rgb, depth)
    assert pairs == [(0, 0), (1, 1)]  # 0.066 is 25 ms from its nearest free depth
    assert (3, 3) not in pairs
    assert len({j for _, j in pairs}) == len(pairs)


def test_reads_frames_interpolates_ground_truth(tmp_path):
    root = write_tum_folder(tmp_path / "rgbd_dataset_freiburg3_x", [0.1, 0.2, 0.3], [0.101, 0.205, 0.31])
    seq = RgbdSequence(root)
    assert len(seq) == 3
    assert seq.camera.fx == pytest.approx(535.4)  # freiburg3 from the folder name
    frame = seq[1]
    assert frame.rgb.shape == (48, 64, 3) and frame.depth_m.dtype == np.float32
    assert frame.depth_m[0, 0] == pytest.approx(1.0)
    # GT x = t, interpolated at the rgb stamps.
    np.testing.assert_allclose(seq.gt_poses[:, 0, 3], [0.1, 0.2, 0.3], atol=1e-9)
    sub = RgbdSequence(root, first=1, last=2)
    assert len(sub) == 2 and sub.timestamps[0] == pytest.approx(0.2)
    # Forward then backward: re-timed forward at the median interval, GT follows the frames.
    there_and_back = RgbdSequence(root, segments=[(0, 2), (1, 0)])
    assert len(there_and_back) == 5 and there_and_back.retimed
    np.testing.assert_allclose(there_and_back.timestamps, 0.1 + 0.1 * np.arange(5))
    np.testing.assert_allclose(there_and_back.gt_poses[:, 0, 3], [0.1, 0.2, 0.3, 0.2, 0.1],
                               atol=1e-9)
    assert there_and_back[3].rgb.shape == frame.rgb.shape


def test_robot_spec_with_frame_ranges():
    assert parse_robot_spec("/data/seq:0-349") == (Path("/data/seq"), [(0, 349)])
    assert parse_robot_spec("/data/seq") == (Path("/data/seq"), None)
    assert parse_robot_spec("s:0-599,598-199") == (Path("s"), [(0, 599), (598, 199)])
    with pytest.raises(ValueError, match="empty"):
        parse_robot_spec("seq:9-3")


@pytest.mark.parametrize("damage, message", [
    (lambda r: (r / "rgb.txt").unlink(), "rgb.txt: cannot read"),
    (lambda r: (r / "depth.txt").write_text("0.1\n"), "depth.txt:1: expected"),
    (lambda r: (r / "depth.txt").write_text("abc depth/x.png\n"), "not a number"),
    (lambda r: (r / "rgb" / "0.200000.png").unlink(), "0.200000.png: listed in the sequence index but missing"),
])
def test_bad_folders_name_the_file(tmp_path, damage, message):
    root = write_tum_folder(tmp_path / "seq", [0.1, 0.2], [0.1, 0.2])
    damage(root)
    with pytest.raises(ValueError, match=message):
        RgbdSequence(root)


def test_bad_ground_truth_is_reported_by_evaluation_only(tmp_path):
    root = write_tum_folder(tmp_path / "seq", [0.1, 0.2], [0.1, 0.2])
    (root / "groundtruth.txt").write_text("0 1 2\n")
    sequence = RgbdSequence(root)  # the running system never reads ground truth
    frame = sequence[1]  # and reads its frames as if the ground truth were fine
    assert (frame.index, frame.timestamp) == (1, 0.2)
    np.testing.assert_array_equal(frame.rgb, frame_rgb(1), strict=True)  # frame 1, RGB order
    np.testing.assert_array_equal(frame.depth_raw, np.full((48, 64), DEPTH_RAW, np.uint16),
                                  strict=True)
    np.testing.assert_array_equal(frame.depth_m, np.ones((48, 64), np.float32), strict=True)
    with pytest.raises(ValueError, match="groundtruth.txt:1: expected 8 values"):
        sequence.gt_poses


def test_undecodable_image_names_the_file(tmp_path):
    root = write_tum_folder(tmp_path / "seq", [0.1, 0.2], [0.1, 0.2])
    (root / "depth" / "0.200000.png").write_bytes(b"not a png")
    seq = RgbdSequence(root)
    with pytest.raises(ValueError, match="0.200000.png: cannot decode depth"):
        seq[1]


def test_no_associable_pairs_is_an_error(tmp_path):
    root = write_tum_folder(tmp_path / "seq", [0.1, 0.2], [0.5, 0.6])
    with pytest.raises(ValueError, match="no rgb/depth pair"):
        RgbdSequence(root)


def test_range_outside_sequence(tmp_path):
    root = write_tum_folder(tmp_path / "seq", [0.1, 0.2], [0.1, 0.2])
    with pytest.raises(ValueError, match="outside"):
        RgbdSequence(root, first=0, last=5)


def test_real_tum_fr1_camera_and_ground_truth():
    seq = RgbdSequence(require(TUM_RPY))
    assert len(seq) == 150
    assert seq.camera.fx == pytest.approx(517.306408) and seq.camera.has_distortion
    assert seq.camera.depth_scale == 5000
    # Its depth images follow OpenNI's factory pinhole, not the calibrated colour camera.
    assert seq.camera.depth_intrinsics == (525.0, 525.0, 319.5, 239.5)
    assert np.isfinite(seq.gt_poses).all()
    frame = seq[0]
    assert 0.3 < np.median(frame.depth_m[frame.depth_m > 0]) < 4.0


def test_real_seven_scenes_camera_depth_scale_and_invalid_values():
    seq = RgbdSequence(require(SEVEN_SCENES))
    assert len(seq) == 600
    assert seq.camera.fx == 585 and seq.camera.depth_scale == 1000
    assert 65535 in seq.camera.invalid_depth
    frame = seq[0]
    assert frame.depth_m.max() < 10.0  # 65535 mm is "no depth", not 65 m
    # The ground truth of frame 0 is the 4x4 of frame-000000.pose.txt.
    pose = np.loadtxt(SEVEN_SCENES / "frame-000000.pose.txt")
    np.testing.assert_allclose(seq.gt_poses[0][:3, 3], pose[:3, 3], atol=1e-5)


@pytest.mark.parametrize("change, message", [
    ({"fx": "abc"}, "fx must be a finite number > 0"),
    ({"fy": -1.0}, "fy must be a finite number > 0"),
    ({"width": 0}, "width must be a whole number"),
    ({"height": 480.5}, "height must be a whole number"),
    ({"distortion": [0.1, 0.2]}, "distortion must be 0, 4, 5 or 8"),
    ({"depth_intrinsics": [525.0, 525.0, 319.5]}, "depth_intrinsics must be empty or 4"),
    ({"depth_intrinsics": [0.0, 525.0, 319.5, 239.5]}, "depth_intrinsics must be empty or 4"),
])
def test_a_camera_that_would_fail_every_frame_is_refused_naming_the_field(change, message):
    from fleetslam.camera import Camera

    good = Camera(525.0, 525.0, 319.5, 239.5).to_dict()
    assert Camera.from_dict(good) == Camera(525.0, 525.0, 319.5, 239.5)
    with pytest.raises(ValueError, match=f"hello camera: {message}"):
        Camera.from_dict({**good, **change}, "hello camera")


def test_a_depth_image_on_its_own_pinhole_is_read_where_the_colour_ray_meets_it():
    """A keypoint's depth is looked up where its (undistorted) colour ray falls in the depth
    image's pinhole, and a depth pixel is back-projected along that pinhole's ray and
    coloured where the ray meets the distorted colour image: the two agree both ways."""
    from fleetslam.camera import TUM_CAMERAS, Camera

    camera = TUM_CAMERAS["freiburg1"]
    fx, fy, cx, cy = camera.depth_intrinsics
    # A slanted plane, so every depth pixel holds a different depth.
    v, u = np.mgrid[0:480, 0:640]
    depth = (1.0 + 0.002 * u + 0.001 * v).astype(np.float32)
    points, vu = camera.backproject_image(depth, stride=8)
    sample = slice(None, None, 97)
    # The depth pixel each point came from, found again from its colour pixel.
    keypoints = vu[sample, ::-1].astype(np.float64)
    found = camera.depth_pixels(keypoints, camera.undistort_points(keypoints))
    expected = np.stack([points[sample, 0] / points[sample, 2] * fx + cx,
                         points[sample, 1] / points[sample, 2] * fy + cy], axis=1)
    np.testing.assert_allclose(found, expected, atol=0.75)  # colour pixels are rounded
    # Without a depth pinhole, depth pixel (u, v) is colour pixel (u, v).
    plain = Camera(525.0, 525.0, 319.5, 239.5)
    np.testing.assert_array_equal(plain.depth_pixels(keypoints, keypoints + 3), keypoints)
    assert Camera.from_dict(camera.to_dict()) == camera
    # A camera restored from a checkpoint written before the field existed has none.
    old = Camera.__new__(Camera)
    old.__dict__.update({k: v for k, v in plain.__dict__.items() if k != "depth_intrinsics"})
    assert old.depth_intrinsics == () and old == plain


@pytest.mark.parametrize("tail", ["0:99", "5", "a-b"])
def test_a_recording_followed_by_no_range_says_what_a_range_looks_like(tmp_path, tail):
    """SEQ:0:99, SEQ:5, SEQ:a-b: the folder exists, what follows it is no range; said so,
    not "no such sequence folder"."""
    with pytest.raises(ValueError, match=rf"'{tail}' after .* is not a frame range: give "
                                         r"FIRST-LAST \(SEQ:0-99\)"):
        parse_robot_spec(f"{tmp_path}:{tail}")
    assert parse_robot_spec(f"{tmp_path / 'nosuch'}:5") == (Path(f"{tmp_path}/nosuch:5"), None)

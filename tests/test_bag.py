"""ROS 1 and ROS 2 bags as a recorded source (datasets/bag.py, datasets/recording.py).

The real-data tests write the shared TUM fr1_rpy frames 0-149 as bags with rosbags' own
writers (bench/bag_writer.py): a ROS 1 bag (rgb8 colour, 32FC1 depth, CameraInfo per topic)
and a ROS 2 MCAP bag (JPEG CompressedImage colour). The bad-input tests write tiny bags.
"""

from __future__ import annotations

import dataclasses
import json
import importlib.util
import sys
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from conftest import PROJECT, TUM_RPY, require

from fleetslam.camera import TUM_CAMERAS, Camera
from fleetslam.config import Config, SourceConfig
from fleetslam.datasets import bag as bag_module
from fleetslam.datasets.bag import BagError, BagSequence
from fleetslam.datasets.recording import open_source
from fleetslam.datasets.ros_messages import MILLIMETRE_DEPTH_SCALE
from fleetslam.datasets.tum import RgbdSequence

_spec = importlib.util.spec_from_file_location("bag_writer", PROJECT / "bench" / "bag_writer.py")
bw = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bw)

FR1 = TUM_CAMERAS["freiburg1"]


# -- tiny bags -------------------------------------------------------------------------

W, H = 8, 6


def tiny_bag(path: Path, flavour: str = "ros1", colour: dict[str, str] | None = None,
             depth: dict[str, str] | None = None, frames: int = 4, info: str = "ok",
             colour_stamps: list[float] | None = None,
             encoding_at: dict[int, str] | None = None) -> Path:
    """A bag of ``frames`` frames of W x H pixels: colour topics {topic: encoding}, depth
    topics {topic: encoding} (depth value (k + 1) * 100 mm at frame k), a CameraInfo beside
    the first colour topic (``info``: "ok", "zeros" or "none"). ``encoding_at``: frame ->
    colour encoding from that frame on."""
    colour = {"/cam/rgb/image": "rgb8"} if colour is None else colour
    depth = {"/cam/depth/image": "16UC1"} if depth is None else depth
    ts = bw.typestore_for(flavour)
    base = 1_600_000_000 * 10**9
    messages = []
    encoding_now = None
    for k in range(frames):
        ns = base + k * 33_333_333
        cns = base + int(colour_stamps[k] * 1e9) if colour_stamps else ns
        encoding_now = (encoding_at or {}).get(k, encoding_now)
        for topic, enc in colour.items():
            enc = encoding_now or enc
            channels = {"rgb8": 3, "bgr8": 3, "yuv422": 2, "mono8": 1}[enc]
            pixels = np.full((H, W, channels), (10 * k + 5) % 256, np.uint8)
            messages.append((topic, bw.IMAGE, cns, bw.image(ts, cns, enc, pixels)))
        for topic, enc in depth.items():
            mm = np.full((H, W), (k + 1) * 100, np.uint16)
            pixels = mm if enc == "16UC1" else (mm / np.float32(1000)).astype(np.float32)
            messages.append((topic, bw.IMAGE, ns, bw.image(ts, ns, enc, pixels)))
        if info != "none":
            first = next(iter(colour)).rsplit("/", 1)[0] if colour else "/cam/rgb"
            values = (0.0, 0.0, 0.0, 0.0) if info == "zeros" else (50.0, 50.0, 3.5, 2.5)
            messages.append((f"{first}/camera_info", bw.CAMERA_INFO, ns,
                             bw.camera_info(ts, ns, *values, W, H)))
    messages.sort(key=lambda m: m[2])
    return bw.write_bag(path, flavour, messages)


def one_line_error(exc: pytest.ExceptionInfo, path: Path, *parts: str) -> str:
    text = str(exc.value)
    assert "\n" not in text
    assert str(path) in text, text
    for part in parts:
        assert part in text, text
    return text


@pytest.mark.parametrize("flavour", ["ros1", "mcap", "sqlite3", "lone-mcap"])
def test_every_bag_kind_plays_its_frames_with_the_camera_info(tmp_path, flavour):
    path = tiny_bag(tmp_path / ("b.bag" if flavour == "ros1" else "b"),
                    "mcap" if flavour == "lone-mcap" else flavour)
    if flavour == "lone-mcap":
        path = next(path.glob("*.mcap"))
    seq = open_source(f"{path}:1-3")
    assert isinstance(seq, BagSequence) and len(seq) == 3 and seq.first == 1
    assert (seq.camera.fx, seq.camera.cx, seq.camera.width) == (50.0, 3.5, W)
    # 16UC1 is millimetres (REP 118): raw values as recorded, at 1000 a metre.
    assert seq.camera.depth_scale == MILLIMETRE_DEPTH_SCALE
    frame = seq[2]
    assert frame.depth_raw[0, 0] == 400 and frame.depth_m[0, 0] == pytest.approx(0.4)
    assert frame.rgb[0, 0].tolist() == [35, 35, 35]
    # The frame's images are its own, as a folder's are (not read-only views of a message).
    assert frame.rgb.flags.writeable and frame.depth_raw.flags.writeable
    assert seq.gt_poses is None and not seq.has_ground_truth


def test_compressed_depth_plays_at_its_encodings_scale(tmp_path):
    import struct

    import cv2

    ts = bw.typestore_for("mcap")
    messages = []
    for k in range(3):
        ns = 1_600_000_000 * 10**9 + k * 33_333_333
        mm = np.full((H, W), (k + 1) * 100, np.uint16)
        payload = struct.pack("<iff", 0, 0.0, 0.0) + cv2.imencode(".png", mm)[1].tobytes()
        messages += [
            ("/cam/rgb/image", bw.IMAGE, ns, bw.image(ts, ns, "bgr8",
                                                       np.full((H, W, 3), (1, 2, 3), np.uint8))),
            ("/cam/depth/image/compressedDepth", bw.COMPRESSED, ns,
             bw.compressed(ts, ns, "16UC1; compressedDepth png", payload)),
            ("/cam/rgb/camera_info", bw.CAMERA_INFO, ns,
             bw.camera_info(ts, ns, 50.0, 50.0, 3.5, 2.5, W, H))]
    seq = open_source(str(bw.write_bag(tmp_path / "b", "mcap", messages)))
    assert seq.depth_topic == "/cam/depth/image/compressedDepth"
    assert seq.camera.depth_scale == MILLIMETRE_DEPTH_SCALE
    assert seq[2].depth_raw[0, 0] == 300 and seq[2].rgb[0, 0].tolist() == [3, 2, 1]


def test_a_depth_camera_info_with_its_own_distortion_is_named(tmp_path):
    from fleetslam.datasets.ros_messages import RosMessageError, camera_from_info

    ts = bw.typestore_for("ros1")
    colour = bw.camera_info(ts, 0, 50.0, 50.0, 3.5, 2.5, W, H, (0.1, 0.01, 0.0, 0.0, 0.0))
    depth = bw.camera_info(ts, 0, 50.0, 50.0, 3.5, 2.5, W, H, (0.1,) + (0.0,) * 7)
    with pytest.raises(RosMessageError, match="^depth.bag topic /d: depth camera with its "
                       "own distortion"):
        camera_from_info(colour, "c.bag topic /c", 1000.0, depth, "depth.bag topic /d")


def test_a_camera_info_the_cloud_would_refuse_is_refused_here(tmp_path):
    """A principal point far outside the image (cx = 50000): `fleetslam run` used to take
    what a cloud refuses in the robot's hello."""
    from fleetslam.datasets.ros_messages import RosMessageError, camera_from_info

    ts = bw.typestore_for("ros1")
    with pytest.raises(RosMessageError, match=r"^c.bag topic /c: CameraInfo: cx must be "
                       r"within 4 image sizes of the image, got 50000.0$"):
        camera_from_info(bw.camera_info(ts, 0, 50.0, 50.0, 50000.0, 2.5, W, H),
                         "c.bag topic /c", 1000.0)


def test_32fc1_depth_is_carried_at_5000_a_metre(tmp_path):
    seq = open_source(str(tiny_bag(tmp_path / "b.bag", depth={"/cam/depth/image": "32FC1"})))
    assert seq.camera.depth_scale == 5000.0
    assert seq[1].depth_raw[0, 0] == 1000 and seq[1].depth_m[0, 0] == pytest.approx(0.2)


def test_unpaired_images_are_counted_and_reported(tmp_path):
    # Colour frame 2 is 0.1 s off any depth image; the pairing tolerance decides.
    stamps = [0.0, 1 / 30, 0.1 + 2 / 30, 3 / 30]
    path = tiny_bag(tmp_path / "b.bag", colour_stamps=stamps)
    seq = open_source(str(path))
    assert (len(seq), seq.unpaired_rgb, seq.unpaired_depth) == (3, 1, 1)
    assert "unpaired 1 colour and 1 depth" in seq.camera_source
    loose = open_source(str(path), source_config=SourceConfig(pair_tolerance_s=0.2))
    assert (len(loose), loose.unpaired_rgb) == (4, 0)


def test_a_repeated_stamp_is_played_once_so_the_run_and_the_cloud_agree(tmp_path):
    """Colour frames 2 and 3 carry one stamp (a driver publishing a frame twice), each paired
    with its own depth image: a cloud refuses the second (its stamp is not after the last
    frame's), so the source leaves it out for every run and says so."""
    stamps = [0.0, 1 / 30, 2.5 / 30, 2.5 / 30, 4 / 30, 5 / 30]
    path = tiny_bag(tmp_path / "b.bag", frames=6, colour_stamps=stamps)
    seq = open_source(str(path))
    assert (seq.pairs, len(seq), seq.repeated) == (6, 5, 1)
    assert np.all(np.diff(seq.timestamps) > 0) and not seq.retimed
    assert "1 frame left out: the stamp repeats the frame's before" in seq.camera_source
    # Played backwards too: the repeat is left out, the rest re-timed forward.
    back = open_source(f"{path}:0-5,4-0")
    assert (len(back), back.repeated) == (5 + 4, 2) and np.all(np.diff(back.timestamps) > 0)
    one = tiny_bag(tmp_path / "one.bag", frames=2, colour_stamps=[0.5 / 30] * 2)
    assert len(open_source(str(one))) == 1
    with pytest.raises(ValueError, match=r"every frame of frames 1-1 repeats the stamp"):
        open_source(f"{one}:1-1")


def test_a_given_camera_overrides_and_keeps_the_depth_topics_scale(tmp_path):
    path = tiny_bag(tmp_path / "b.bag", info="none")
    with pytest.raises(BagError) as exc:
        open_source(str(path))
    one_line_error(exc, path, "no CameraInfo for /cam/rgb/image", "--camera camera.json")
    seq = open_source(str(path), Camera(40.0, 40.0, 4.0, 3.0, W, H))
    assert seq.camera_source.startswith("given") and seq.camera.fx == 40.0
    assert seq.camera.depth_scale == MILLIMETRE_DEPTH_SCALE


def test_a_missing_bag_is_named_as_a_bag(tmp_path):
    with pytest.raises(BagError) as exc:
        open_source(f"{tmp_path / 'gone.bag'}:0-9")
    one_line_error(exc, tmp_path / "gone.bag", "no such bag")


def test_a_bag_without_image_topics_is_refused(tmp_path):
    path = tiny_bag(tmp_path / "b.bag", colour={}, depth={})  # CameraInfo only
    with pytest.raises(BagError) as exc:
        open_source(str(path))
    one_line_error(exc, path, "no colour image topic", "image topics: none")


def test_two_colour_topics_are_listed_and_a_flag_chooses(tmp_path):
    path = tiny_bag(tmp_path / "b.bag", colour={"/a/image": "rgb8", "/b/image": "bgr8"})
    with pytest.raises(BagError) as exc:
        open_source(str(path))
    one_line_error(exc, path, "2 colour image topics", "--rgb-topic",
                   "/a/image (sensor_msgs/msg/Image rgb8, 4 messages)",
                   "/b/image (sensor_msgs/msg/Image bgr8, 4 messages)")
    seq = open_source(str(path), source_config=SourceConfig(rgb_topic="/b/image"))
    assert seq.rgb_topic == "/b/image" and seq[0].rgb[0, 0].tolist() == [5, 5, 5]


RS = "/camera/camera"  # the RealSense ROS 2 driver's namespace


def realsense_bag(path: Path) -> Path:
    """A bag laid out as the RealSense driver records: raw colour with its JPEG
    image_transport copy, unaligned depth (200 mm) and depth aligned to colour (700 mm)
    with its compressedDepth copy, CameraInfo beside each."""
    import struct

    import cv2

    ts = bw.typestore_for("mcap")
    messages = []
    for k in range(3):
        ns = 1_600_000_000 * 10**9 + k * 33_333_333
        rgb = np.full((H, W, 3), (1, 2, 3), np.uint8)
        aligned = np.full((H, W), 700, np.uint16)
        coded_depth = struct.pack("<iff", 0, 0.0, 0.0) + cv2.imencode(".png", aligned)[1].tobytes()
        for topic, kind, msg in (
                (f"{RS}/color/image_raw", bw.IMAGE, bw.image(ts, ns, "rgb8", rgb)),
                (f"{RS}/color/image_raw/compressed", bw.COMPRESSED,
                 bw.compressed(ts, ns, "rgb8; jpeg compressed bgr8",
                               cv2.imencode(".jpg", rgb)[1].tobytes())),
                (f"{RS}/depth/image_rect_raw", bw.IMAGE,
                 bw.image(ts, ns, "16UC1", np.full((H, W), 200, np.uint16))),
                (f"{RS}/aligned_depth_to_color/image_raw", bw.IMAGE,
                 bw.image(ts, ns, "16UC1", aligned)),
                (f"{RS}/aligned_depth_to_color/image_raw/compressedDepth", bw.COMPRESSED,
                 bw.compressed(ts, ns, "16UC1; compressedDepth png", coded_depth))):
            messages.append((topic, kind, ns, msg))
        for where in ("color", "depth", "aligned_depth_to_color"):
            messages.append((f"{RS}/{where}/camera_info", bw.CAMERA_INFO, ns,
                             bw.camera_info(ts, ns, 50.0, 50.0, 3.5, 2.5, W, H)))
    return bw.write_bag(path, "mcap", messages)


def test_a_realsense_bag_plays_aligned_depth_and_raw_colour_and_says_why(tmp_path, caplog):
    """Issue 45 item 2: such a bag failed with "2 depth image topics"; the topics a user
    means are chosen, in one log line that names the others and why they were passed over."""
    path = realsense_bag(tmp_path / "rs")
    with caplog.at_level("INFO", logger="fleetslam.datasets.bag"):
        seq = open_source(str(path))
    assert seq.rgb_topic == f"{RS}/color/image_raw"
    assert seq.depth_topic == f"{RS}/aligned_depth_to_color/image_raw"
    assert seq[1].depth_raw[0, 0] == 700 and seq[1].rgb[0, 0].tolist() == [1, 2, 3]
    lines = [r.getMessage() for r in caplog.records if "chosen over" in r.getMessage()]
    assert len(lines) == 1, caplog.text
    for part in (f"colour {RS}/color/image_raw and depth {RS}/aligned_depth_to_color/image_raw",
                 f"{RS}/color/image_raw/compressed (image_transport copy of "
                 f"{RS}/color/image_raw)",
                 f"{RS}/aligned_depth_to_color/image_raw/compressedDepth (image_transport copy",
                 f"{RS}/depth/image_rect_raw (not aligned to colour)"):
        assert part in lines[0], lines[0]
    # The flags still win, and then nothing is said to be passed over for that role.
    caplog.clear()
    with caplog.at_level("INFO", logger="fleetslam.datasets.bag"):
        seq = open_source(str(path), source_config=SourceConfig(
            rgb_topic=f"{RS}/color/image_raw/compressed",
            depth_topic=f"{RS}/depth/image_rect_raw"))
    assert (seq.rgb_topic, seq.depth_topic) == (f"{RS}/color/image_raw/compressed",
                                                f"{RS}/depth/image_rect_raw")
    assert seq[0].depth_raw[0, 0] == 200 and "chosen over" not in caplog.text


def test_two_aligned_depth_topics_are_still_for_the_user_to_choose(tmp_path):
    path = tiny_bag(tmp_path / "b.bag", depth={"/a/aligned_depth_to_color/image_raw": "16UC1",
                                               "/b/depth_registered/image_raw": "16UC1",
                                               "/c/depth/image_raw": "16UC1"})
    with pytest.raises(BagError) as exc:
        open_source(str(path))
    one_line_error(exc, path, "2 depth image topics", "--depth-topic")


def test_an_unsupported_encoding_is_named(tmp_path):
    path = tiny_bag(tmp_path / "b.bag", colour={"/cam/rgb/image": "yuv422"})
    with pytest.raises(BagError) as exc:
        open_source(str(path))
    one_line_error(exc, path, "no colour image topic", "yuv422", "/cam/rgb/image")
    with pytest.raises(BagError) as exc:
        open_source(str(path), source_config=SourceConfig(rgb_topic="/cam/rgb/image"))
    one_line_error(exc, path, "topic /cam/rgb/image", "unsupported encoding ('yuv422')")


def test_an_encoding_change_mid_topic_is_refused(tmp_path):
    path = tiny_bag(tmp_path / "b.bag", encoding_at={2: "bgr8"})
    with pytest.raises(BagError) as exc:
        open_source(str(path))
    one_line_error(exc, path, "topic /cam/rgb/image", "changes from 'rgb8' to 'bgr8'")


@pytest.mark.parametrize("flavour", ["ros1", "mcap"])
def test_a_truncated_bag_is_refused(tmp_path, flavour):
    whole = tiny_bag(tmp_path / ("w.bag" if flavour == "ros1" else "w"), flavour, frames=30)
    whole = whole if flavour == "ros1" else next(whole.glob("*.mcap"))
    cut = tmp_path / f"cut{whole.suffix}"
    data = whole.read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(BagError) as exc:
        open_source(str(cut))
    one_line_error(exc, cut, "not a readable ROS bag")


def test_an_uncalibrated_camera_info_is_refused_through_the_cli(tmp_path, capsys):
    from fleetslam.cli import main

    path = tiny_bag(tmp_path / "b.bag", info="zeros")
    with pytest.raises(ValueError) as exc:  # ros_messages.RosMessageError
        open_source(str(path))
    one_line_error(exc, path, "topic /cam/rgb/camera_info", "not calibrated")
    assert main(["--quiet", "run", "--robot", str(path), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("fleetslam: error: ") and "not calibrated" in err
    assert "Traceback" not in err and not (tmp_path / "o").exists()


def test_the_cli_topic_flags_reach_the_source_config(tmp_path, capsys):
    from fleetslam.cli import main

    path = tiny_bag(tmp_path / "b.bag", colour={"/a/image": "rgb8", "/b/image": "rgb8"})
    code = main(["--quiet", "plan", "--source", str(path), "--rgb-topic", "/nope",
                 "--out", str(tmp_path / "p")])
    assert code == 2
    assert "--rgb-topic /nope is not an image topic" in capsys.readouterr().err


def test_without_the_ros_extra_a_bag_names_it_and_folders_still_play(tmp_path, monkeypatch):
    import cv2

    folder = tmp_path / "seq"
    (folder / "rgb").mkdir(parents=True)
    (folder / "depth").mkdir()
    cv2.imwrite(str(folder / "rgb" / "0.png"), np.zeros((H, W, 3), np.uint8))
    cv2.imwrite(str(folder / "depth" / "0.png"), np.ones((H, W), np.uint16))
    (folder / "rgb.txt").write_text("1.0 rgb/0.png\n")
    (folder / "depth.txt").write_text("1.0 depth/0.png\n")
    path = tiny_bag(tmp_path / "b.bag")
    for name in [m for m in sys.modules if m == "rosbags" or m.startswith("rosbags.")]:
        monkeypatch.setitem(sys.modules, name, None)  # import raises ModuleNotFoundError
    assert len(open_source(str(folder))) == 1
    with pytest.raises(BagError) as exc:
        open_source(str(path))
    one_line_error(exc, path, "needs the ros extra: pip install 'fleetslam[ros]'")


def test_a_robot_without_the_ros_extra_is_told_through_the_cli(tmp_path):
    """In a process where rosbags is not installed (simulated): the CLI names the extra."""
    import subprocess

    path = tiny_bag(tmp_path / "b.bag")
    code = f"""
import sys
sys.modules["rosbags"] = None  # import raises ModuleNotFoundError
from fleetslam.cli import main
print(main(["--quiet", "robot", "--id", "r1", "--source", "{path}:0-1"]))
print(sorted(m for m in sys.modules if m.startswith("rosbags")))
"""
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert run.stdout.split("\n")[:2] == ["2", "['rosbags']"], run.stdout + run.stderr
    assert run.stderr.startswith(f"fleetslam: error: {path}: reading a ROS bag needs the ros "
                                 f"extra: pip install 'fleetslam[ros]'"), run.stderr
    assert "Traceback" not in run.stderr


# -- the real sequence as bags ---------------------------------------------------------


@pytest.fixture(scope="session")
def tum_bags(tmp_path_factory) -> dict[str, Path]:
    folder = require(TUM_RPY)
    out = tmp_path_factory.mktemp("bags")
    ros1 = bw.write_tum_bag(folder, out / "fr1_rpy.bag", "ros1", FR1, "rgb8")
    mcap = bw.write_tum_bag(folder, out / "fr1_rpy_jpeg", "mcap", FR1, "jpeg")
    return {"ros1": ros1, "mcap": mcap, "lone_mcap": next(mcap.glob("*.mcap"))}


@pytest.fixture(scope="session")
def folder_run():
    from fleetslam.system import track_robot

    folder = require(TUM_RPY)
    return track_robot("r0", str(folder), RgbdSequence(folder), Config(), False)


@pytest.mark.realdata
@pytest.mark.parametrize("kind", ["ros1", "lone_mcap"])
def test_the_bags_camera_is_tums_freiburg1(tum_bags, kind):
    seq = open_source(str(tum_bags[kind]))
    assert dataclasses.asdict(seq.camera) == dataclasses.asdict(FR1)
    assert seq.camera_source.startswith("CameraInfo /camera/rgb/camera_info, depth pinhole "
                                        "from /camera/depth/camera_info; 150 colour/depth")


@pytest.mark.realdata
def test_frame_ranges_of_a_bag_are_the_folders_frames(tum_bags):
    folder = require(TUM_RPY)
    seq = open_source(f"{tum_bags['ros1']}:10-59")
    ref = RgbdSequence(folder, first=10, last=59)
    assert len(seq) == 50 and seq.first == 10
    np.testing.assert_array_equal(seq.timestamps, ref.timestamps)
    for i in (0, 1, 2, 25, 49):
        a, b = seq[i], ref[i]
        np.testing.assert_array_equal(a.rgb, b.rgb)
        np.testing.assert_array_equal(a.depth_raw, b.depth_raw)
        np.testing.assert_array_equal(a.depth_m, b.depth_m)
    # There and back: re-timed as the folder is, and the backward frames are the right ones.
    back = open_source(f"{tum_bags['ros1']}:0-20,19-5")
    ref = RgbdSequence(folder, segments=[(0, 20), (19, 5)])
    assert back.retimed and ref.retimed
    np.testing.assert_array_equal(back.timestamps, ref.timestamps)
    np.testing.assert_array_equal(back[30].depth_raw, ref[30].depth_raw)


@pytest.mark.realdata
def test_play_continues_one_stream_and_a_jump_back_keeps_its_place(tum_bags, monkeypatch):
    folder = require(TUM_RPY)
    seeks = {"n": 0}
    seek = bag_module._MessageStream._seek

    def counting(self, start):
        seeks["n"] += 1
        seek(self, start)

    monkeypatch.setattr(bag_module._MessageStream, "_seek", counting)
    seq = open_source(f"{tum_bags['mcap']}:0-59")
    ref = RgbdSequence(folder, last=59)
    for i in range(40):
        seq[i]
    assert seeks["n"] == 1  # the whole play so far from one seek
    # An old keyframe read again (the robot's uploader, the dense map) is that frame...
    np.testing.assert_array_equal(seq[7].depth_raw, ref[7].depth_raw)
    assert seeks["n"] == 2
    # ...and play goes on where it was, without seeking again.
    for i in range(40, 60):
        np.testing.assert_array_equal(seq[i].depth_raw, ref[i].depth_raw)
    assert seeks["n"] == 2


@pytest.mark.realdata
def test_the_index_pass_holds_no_images(tum_bags):
    size = tum_bags["ros1"].stat().st_size  # ~320 MB
    tracemalloc.start()
    try:
        seq = open_source(str(tum_bags["ros1"]))
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert len(seq) == 150
    # One message (and rosbags' chunk) at a time: ~10 MB (rosbags' imports and type
    # parsing included), where the images are 320.
    assert peak < size / 10, f"peak {peak / 1e6:.1f} MB for a {size / 1e6:.0f} MB bag"


@pytest.mark.realdata
def test_fleetslam_run_on_the_lossless_bag_gives_the_folders_poses(tum_bags, folder_run,
                                                                   tmp_path):
    from fleetslam.cli import main
    from fleetslam.io.trajectory import read_tum_trajectory

    from fleetslam.evaluation.fleet import run_ate

    out = tmp_path / "run"
    # A bag carries no ground truth: the recording's file is given (issue 45 item 3).
    gt = TUM_RPY / "groundtruth.txt"
    assert main(["--quiet", "run", "--robot", str(tum_bags["ros1"]), "--groundtruth", str(gt),
                 "--out", str(out)]) == 0
    times, poses = read_tum_trajectory(out / "r0" / "trajectory.tum")
    assert len(poses) == 150
    np.testing.assert_allclose(times, folder_run.timestamps, atol=1e-6)
    np.testing.assert_allclose(poses[:, :3, 3], folder_run.poses[:, :3, 3], atol=1e-6)
    np.testing.assert_allclose(poses[:, :3, :3], folder_run.poses[:, :3, :3], atol=1e-6)
    text = (out / "summary.json").read_text()
    assert "unpaired 0 colour and 0 depth" in text
    robot = json.loads(text)["robots"][0]
    assert robot["groundtruth"] == str(gt.resolve())
    assert robot["ate"]["rmse_m"] == pytest.approx(run_ate(folder_run)["rmse_m"], abs=1e-6)
    # The report made later reads the bag's file again from summary.json.
    assert main(["--quiet", "report", str(out)]) == 0
    page = (out / "report" / "report.html").read_text()
    assert "a bag carries no ground truth" not in page and "error_over_time.png" in page


@pytest.mark.realdata
def test_the_jpeg_bag_tracks_within_ten_percent_of_the_folders_ate(tum_bags, folder_run):
    from fleetslam.evaluation.fleet import ate_summary, ground_truth_at, run_ate
    from fleetslam.system import track_robot

    folder = RgbdSequence(require(TUM_RPY))
    run = track_robot("r0", str(tum_bags["mcap"]), open_source(str(tum_bags["mcap"])),
                      Config(), False)
    ok, gt = ground_truth_at(run.timestamps, folder)  # the bag has none: the folder's
    assert ok.all()
    bag_ate = ate_summary(run.poses[ok], gt)["rmse_m"]
    folder_ate = run_ate(folder_run)["rmse_m"]
    assert bag_ate <= 1.10 * folder_ate, (bag_ate, folder_ate)


def _claiming(png: bytes, width: int, height: int) -> bytes:
    """``png`` with its IHDR claiming width x height (its CRC made right): a small message
    that would decode to a huge image."""
    import struct
    import zlib

    ihdr = png[12:16] + struct.pack(">II", width, height) + png[24:29]
    return png[:8] + png[8:12] + ihdr + struct.pack(">I", zlib.crc32(ihdr)) + png[33:]


def test_a_compressed_image_is_sized_from_its_header_before_it_is_decoded():
    """A PNG whose header claims 20000 x 20000 pixels (a decompression bomb) is refused
    before decoding, as colour and as compressedDepth; one of another size than the camera's
    too, where the camera is known (a live ROS 2 topic)."""
    import struct

    import cv2

    from fleetslam.datasets.ros_messages import RosMessageError, colour_image, depth_image

    ts = bw.typestore_for("mcap")
    png = cv2.imencode(".png", np.full((H, W, 3), 7, np.uint8))[1].tobytes()
    bomb = bw.compressed(ts, 0, "png", _claiming(png, 20000, 20000))
    with pytest.raises(RosMessageError, match=r"^c: compressed image \('png'\) not decoded: "
                       r"20000 x 20000 pixels exceed the limit of 16777216$"):
        colour_image(bomb, "c")
    assert colour_image(bw.compressed(ts, 0, "png", png), "c", (W, H)).shape == (H, W, 3)
    with pytest.raises(RosMessageError, match=rf"not decoded: {W} x {H} pixels, the camera's "
                       r"images are 640 x 480$"):
        colour_image(bw.compressed(ts, 0, "png", png), "c", (640, 480))
    depth_png = cv2.imencode(".png", np.full((H, W), 500, np.uint16))[1].tobytes()
    depth = bw.compressed(ts, 0, "16UC1; compressedDepth png",
                          struct.pack("<iff", 0, 0.0, 0.0) + _claiming(depth_png, 20000, 20000))
    with pytest.raises(RosMessageError, match="compressedDepth payload not decoded: 20000 x"):
        depth_image(depth, "d", MILLIMETRE_DEPTH_SCALE)
    with pytest.raises(RosMessageError, match=r"is neither PNG nor JPEG"):
        colour_image(bw.compressed(ts, 0, "png", b"GIF89a" + bytes(40)), "c")

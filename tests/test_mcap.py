"""run.mcap, the run's results as ROS 2 messages, read back with the mcap library and
mcap_ros2's decoder (not ours) against the files the run wrote: the two-robot synthetic run
that test_system.py checks (conftest.synthetic_run)."""

from __future__ import annotations

import json
import re
from collections import Counter
from pathlib import Path

import numpy as np
import octomap
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from conftest import mcap_messages

from fleetslam.cli import main
from fleetslam.config import Config
from fleetslam.datasets.recording import open_source
from fleetslam.io.ply import read_ply
from fleetslam.system import run_fleet


def _decoded(path: Path) -> dict[str, list]:
    """topic: its decoded messages, in log-time order."""
    out: dict[str, list] = {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, channel, _, message in reader.iter_decoded_messages(log_time_order=True):
            out.setdefault(channel.topic, []).append(message)
    return out


def _tum(path: Path) -> np.ndarray:
    """The rows of a TUM file (t tx ty tz qx qy qz qw), read with numpy alone."""
    return np.loadtxt(path, comments="#", ndmin=2)


def _ns(stamp) -> int:
    return stamp.sec * 1_000_000_000 + stamp.nanosec


def _assert_poses(stamps: list, translations: np.ndarray, quaternions: np.ndarray,
                  tum: np.ndarray) -> None:
    assert [_ns(s) for s in stamps] == [round(t * 1e9) for t in tum[:, 0]]
    np.testing.assert_allclose(translations, tum[:, 1:4], atol=1e-8)
    # q and -q are one rotation.
    dots = np.abs(np.sum(quaternions * tum[:, 4:8], axis=1))
    np.testing.assert_allclose(dots, 1.0, atol=1e-8)


@pytest.fixture(scope="module")
def run(synthetic_run):
    out, summary = synthetic_run
    return out, summary, _decoded(out / "run.mcap")


def test_the_run_writes_run_mcap_with_each_topic_and_ros2_schemas(run):
    out, summary, _ = run
    assert summary["mcap"] == "run.mcap"
    assert json.loads((out / "summary.json").read_text())["mcap"] == "run.mcap"
    messages = mcap_messages(out / "run.mcap")
    counts = Counter(topic for topic, _, _, _ in messages)
    frames = {r["name"]: r["frames"] for r in summary["robots"]}
    assert counts == {
        "/r0/path": 1, "/r1/path": 1, "/r0/global_path": 1, "/r1/global_path": 1,
        "/r0/map": 1, "/r1/map": 1, "/tf": sum(frames.values()), "/tf_static": 1,
        "/map/global": 1, "/map/octomap": 1, "/map/constraints": 1, "/map/grid": 1}
    schemas = {topic: schema for topic, schema, _, _ in messages}
    assert schemas["/tf"] == schemas["/tf_static"] == "tf2_msgs/msg/TFMessage"
    assert schemas["/r0/path"] == "nav_msgs/msg/Path"
    assert schemas["/map/global"] == "sensor_msgs/msg/PointCloud2"
    assert schemas["/map/octomap"] == "octomap_msgs/msg/Octomap"
    assert schemas["/map/constraints"] == "visualization_msgs/msg/MarkerArray"
    assert schemas["/map/grid"] == "nav_msgs/msg/OccupancyGrid"
    # rosbag2's offered QoS on every channel (the ros2 profile's): the results known at the
    # end are latched (transient local), so rviz2's /tf_static subscriber matches them.
    with open(out / "run.mcap", "rb") as f:
        channels = make_reader(f).get_summary().channels.values()
    durability = {c.topic: int(re.search(r"^  durability: (\d)$", c.metadata[
        "offered_qos_profiles"], re.M).group(1)) for c in channels}
    assert durability == {topic: 2 if topic == "/tf" else 1 for topic in counts}
    # Time moves forward through the file (players stream it).
    times = [t for _, _, t, _ in messages]
    assert times == sorted(times)


def test_point_clouds_equal_the_plys(run):
    out, summary, topics = run
    for topic, ply, frame in [("/r0/map", out / "r0" / "map.ply", "r0/map"),
                              ("/r1/map", out / "r1" / "map.ply", "r1/map"),
                              ("/map/global", out / "global_map.ply", "map")]:
        (cloud,) = topics[topic]
        assert cloud.header.frame_id == frame
        fields = {f.name: (f.offset, f.datatype, f.count) for f in cloud.fields}
        assert fields == {"x": (0, 7, 1), "y": (4, 7, 1), "z": (8, 7, 1), "rgb": (12, 7, 1)}
        assert not cloud.is_bigendian and cloud.height == 1
        assert cloud.row_step == cloud.point_step * cloud.width
        rows = np.frombuffer(bytes(cloud.data), np.dtype({
            "names": ["x", "y", "z", "rgb"], "formats": ["<f4", "<f4", "<f4", "<u4"],
            "offsets": [fields[n][0] for n in ("x", "y", "z", "rgb")],
            "itemsize": cloud.point_step}))
        points, colors = read_ply(ply)
        assert cloud.width == len(points) > 1000
        xyz = np.stack([rows["x"], rows["y"], rows["z"]], axis=1)
        np.testing.assert_array_equal(xyz, points.astype(np.float32))
        # rviz / Foxglove's packed colour: 0x00RRGGBB in a float32 field's bytes.
        rgb = np.stack([(rows["rgb"] >> 16) & 255, (rows["rgb"] >> 8) & 255,
                        rows["rgb"] & 255], axis=1)
        np.testing.assert_array_equal(rgb, colors)


def test_paths_and_transforms_equal_the_trajectories(run):
    out, summary, topics = run
    merge = summary["merge"]
    tf = [t for message in topics["/tf"] for t in message.transforms]
    for robot in summary["robots"]:
        name = robot["name"]
        for topic, tum_file, frame in [
                (f"/{name}/path", out / robot["trajectory"], f"{name}/map"),
                (f"/{name}/global_path", out / "global" / f"{name}.tum", "map")]:
            (path,) = topics[topic]
            tum = _tum(tum_file)
            assert path.header.frame_id == frame and len(path.poses) == len(tum)
            assert {p.header.frame_id for p in path.poses} == {frame}
            _assert_poses([p.header.stamp for p in path.poses],
                          np.array([[p.pose.position.x, p.pose.position.y, p.pose.position.z]
                                    for p in path.poses]),
                          np.array([[p.pose.orientation.x, p.pose.orientation.y,
                                     p.pose.orientation.z, p.pose.orientation.w]
                                    for p in path.poses]), tum)
        # A merged robot's camera in the global frame, every frame at its time.
        camera = [t for t in tf if t.child_frame_id == f"{name}/camera"]
        assert {t.header.frame_id for t in camera} == {"map"}
        _assert_poses([t.header.stamp for t in camera],
                      np.array([[t.transform.translation.x, t.transform.translation.y,
                                 t.transform.translation.z] for t in camera]),
                      np.array([[t.transform.rotation.x, t.transform.rotation.y,
                                 t.transform.rotation.z, t.transform.rotation.w]
                                for t in camera]), _tum(out / "global" / f"{name}.tum"))
    # Each robot's map frame where the merge placed it.
    (static,) = topics["/tf_static"]
    placed = {t.child_frame_id: t for t in static.transforms}
    assert set(placed) == {"r0/map", "r1/map"}
    for name in ("r0", "r1"):
        t = placed[f"{name}/map"]
        assert t.header.frame_id == "map"
        T = np.array(merge["T_global_map"][name])
        np.testing.assert_allclose([t.transform.translation.x, t.transform.translation.y,
                                    t.transform.translation.z], T[:3, 3], atol=1e-9)
        x, y, z, w = (t.transform.rotation.x, t.transform.rotation.y,
                      t.transform.rotation.z, t.transform.rotation.w)
        R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                      [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                      [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
        np.testing.assert_allclose(R, T[:3, :3], atol=1e-8)


def test_the_octomap_message_is_the_bt_files_tree(run):
    out, _, topics = run
    (message,) = topics["/map/octomap"]
    assert message.header.frame_id == "map"
    assert message.binary and message.id == "OcTree" and message.resolution == 0.05
    data = np.array(message.data, np.int8).tobytes()
    # octomap_msgs' binaryMsgToMap reads the data as readBinaryData does: the tree alone.
    # octomap-python reads a binary stream through its file header, so put one in front.
    bt = octomap.OcTree(str(out / "global_map.bt").encode())
    header = (f"# Octomap OcTree binary file\nid OcTree\nsize {bt.size()}\n"
              f"res {message.resolution}\ndata\n").encode()
    tree = octomap.OcTree(0.1)
    assert tree.readBinary(header + data)
    assert tree.getResolution() == 0.05
    assert tree.getNumLeafNodes() == bt.getNumLeafNodes() > 1000
    assert (out / "global_map.bt").read_bytes().endswith(data)


def test_constraints_are_lines_between_keyframes_in_the_global_frame(run):
    out, summary, topics = run
    constraints = summary["merge"]["constraints"]
    (array,) = topics["/map/constraints"]
    kept, rejected = array.markers
    assert (kept.type, kept.ns, kept.header.frame_id) == (5, "constraints", "map")
    ends = {True: kept.points, False: rejected.points}
    for flag, points in ends.items():
        chosen = [c for c in constraints if c["kept"] is flag]
        assert len(points) == 2 * len(chosen)
        xyz = np.array([[p.x, p.y, p.z] for p in points]).reshape(-1, 2, 3)
        # Each end is its keyframe's camera centre: that frame's global pose.
        for (query, place), c in zip(xyz, chosen):
            for end, robot, frame in [(query, c["query_robot"], c["query_frame"]),
                                      (place, c["place_robot"], c["place_frame"])]:
                tum = _tum(out / "global" / f"{robot}.tum")
                np.testing.assert_allclose(end, tum[frame, 1:4], atol=1e-6)
    assert len(kept.points) >= 2


def test_the_grid_message_is_the_nav2_map(run):
    """/map/grid (decoded by mcap-ros2-support) holds global_map.pgm: its cells, bottom row
    first, as -1 / 0 / 100, its origin the lower-left corner placed in the map frame."""
    import cv2

    from fleetslam.transforms import T_from_tum, transform_points

    out, summary, topics = run
    (grid,) = topics["/map/grid"]
    entry = summary["merge"]["grid"]
    image = cv2.imread(str(out / "global_map.pgm"), cv2.IMREAD_UNCHANGED)
    assert grid.header.frame_id == "map" and (grid.info.width, grid.info.height) == \
        (image.shape[1], image.shape[0])
    cells = np.asarray(grid.data, np.int8).reshape(image.shape)[::-1]
    assert ((cells == 100) == (image == 0)).all() and ((cells == 0) == (image == 254)).all()
    assert ((cells == -1) == (image == 205)).all()
    o = grid.info.origin
    T_origin = T_from_tum(np.array([[o.position.x, o.position.y, o.position.z,
                                     o.orientation.x, o.orientation.y, o.orientation.z,
                                     o.orientation.w]]))[0]
    T_map_grid = np.array(entry["T_map_grid"])
    expected = transform_points(T_map_grid, np.array([[*entry["origin"][:2], 0.0]]))[0]
    np.testing.assert_allclose(T_origin[:3, 3], expected, atol=1e-9)
    np.testing.assert_allclose(T_origin[:3, :3], T_map_grid[:3, :3], atol=1e-9)


def test_export_of_the_run_folder_writes_the_same_messages(run, tmp_path, capsys):
    out, _, _ = run
    exported = tmp_path / "export.mcap"
    assert main(["--quiet", "export", str(out), "--mcap", str(exported)]) == 0
    assert capsys.readouterr().out.strip() == str(exported)
    assert mcap_messages(exported) == mcap_messages(out / "run.mcap")


def test_export_names_a_folder_that_is_not_a_run(tmp_path, capsys):
    assert main(["--quiet", "export", str(tmp_path), "--mcap", str(tmp_path / "x.mcap")]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"fleetslam: error: {tmp_path / 'summary.json'}: no summary.json: not a " \
                  "finished run folder"
    assert not (tmp_path / "x.mcap").exists()
    (tmp_path / "summary.json").write_text(json.dumps({"robots": [{"name": "r0"}]}))
    assert main(["--quiet", "export", str(tmp_path), "--mcap", str(tmp_path / "x.mcap")]) == 2
    assert capsys.readouterr().err.strip() == (
        f"fleetslam: error: {tmp_path / 'summary.json'}: not a fleetslam run summary "
        "(no 'trajectory' entry)")
    assert not (tmp_path / "x.mcap").exists()


def test_outputs_mcap_false_writes_none(synthetic_scene, tmp_path):
    config = Config().with_values({"outputs.mcap": False})
    source = f"{synthetic_scene[1][0]}:0-7"
    out = tmp_path / "solo"
    summary = run_fleet([("solo", source, open_source(source))], config, out, False)
    assert (out / "summary.json").exists() and not (out / "run.mcap").exists()
    assert "mcap" not in summary


def test_a_lone_robot_has_its_level_map_too(synthetic_scene, tmp_path):
    """One robot: its map made level is the run's global map (map_frame.py), so run.mcap
    places it in ``map`` as a merge's would be."""
    source = f"{synthetic_scene[1][0]}:0-7"
    out = tmp_path / "solo"
    summary = run_fleet([("solo", source, open_source(source))], Config(), out, False)
    topics = _decoded(out / "run.mcap")
    assert {"/solo/path", "/solo/map", "/tf", "/tf_static", "/map/global", "/map/grid",
            "/solo/global_path"} <= set(topics)
    tf = [t for message in topics["/tf"] for t in message.transforms]
    assert {(t.header.frame_id, t.child_frame_id) for t in tf} == {("map", "solo/camera")}
    assert len(tf) == 8
    (static,) = [t for message in topics["/tf_static"] for t in message.transforms]
    assert (static.header.frame_id, static.child_frame_id) == ("map", "solo/map")
    T = np.array(summary["merge"]["T_global_map"]["solo"])
    np.testing.assert_allclose([static.transform.translation.x, static.transform.translation.y,
                                static.transform.translation.z], T[:3, 3], atol=1e-9)

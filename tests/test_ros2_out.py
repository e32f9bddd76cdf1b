"""Live ROS 2 out (ros2_out/, edge/ros2_out.py, cloud/merge/fleet_frames.py): what fleetslam
publishes is checked against implementations we did not write. The messages byte for byte
against rosbags' CDR serialiser and its REP-2016 type hashes; keys, tokens and transient
local through zenoh-ros2-sdk's subscriber and zenoh-ext's AdvancedSubscriber (what
rmw_zenoh's own subscriptions are); the poses and the fleet frame end to end against the
run's files.
"""

from __future__ import annotations

import json
import logging
import struct
import threading
import time

import numpy as np
import pytest

from conftest import TUM_RPY, require, wait_for
from fleetslam.config import Config
from fleetslam.datasets.rmw_zenoh import (
    key_topic,
    key_type,
    make_attachment,
    parse_attachment,
    parse_liveliness,
)
from fleetslam.ros2_out import cdr
from fleetslam.transforms import T_from_tum, make_T, rotation_exp, tum_from_T
from fleetslam.transforms import invert as invert_T
from fleetslam.transport import protocol


def _typestore():
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def _pose(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return make_T(rotation_exp(rng.normal(size=3)), rng.normal(size=3))


def _message_T(pose) -> np.ndarray:
    """A decoded Pose or Transform as 4 x 4."""
    p = getattr(pose, "position", None) or pose.translation
    q = getattr(pose, "orientation", None) or pose.rotation
    return T_from_tum(np.array([[p.x, p.y, p.z, q.x, q.y, q.z, q.w]]))[0]


def _stamp_ns(header) -> int:
    return header.stamp.sec * 1_000_000_000 + header.stamp.nanosec


# ---------------------------------------------------------------------------- messages


@pytest.mark.parametrize("frame", ["", "m", "r1/map", "a_frame_of_odd_length"])
def test_messages_are_what_rosbags_serialises_byte_for_byte(frame):
    """Each message decodes with the standard definitions and re-serialises to the same
    bytes (every alignment exercised: frame ids of 0-21 characters shift what follows)."""
    store = _typestore()
    stamp = 1_305_031_229_528_748_000
    T, U = _pose(1), _pose(2)
    made = {
        cdr.POSE_STAMPED: cdr.pose_stamped(stamp, frame, T),
        cdr.TF_MESSAGE: cdr.tf_message([(stamp, frame, "r1/camera", T),
                                        (stamp + 1, "map", frame + "x", U)]),
        cdr.PATH: cdr.path(stamp, frame, [stamp - 7, stamp], np.stack([T, U])),
        cdr.DIAGNOSTIC_ARRAY: cdr.diagnostic_array(stamp, [
            (cdr.WARN, "fleetslam r1: tracking", "lost", "r1", [("state", "lost"),
                                                              ("frames", "12")]),
            (cdr.OK, "x", "", frame, [])]),
    }
    for ros_type, data in made.items():
        message = store.deserialize_cdr(data, ros_type)
        assert bytes(store.serialize_cdr(message, ros_type)) == data, ros_type
    pose = store.deserialize_cdr(made[cdr.POSE_STAMPED], cdr.POSE_STAMPED)
    assert _stamp_ns(pose.header) == stamp and pose.header.frame_id == frame
    np.testing.assert_allclose(_message_T(pose.pose), T, atol=1e-12)
    tf = store.deserialize_cdr(made[cdr.TF_MESSAGE], cdr.TF_MESSAGE).transforms
    assert [(t.header.frame_id, t.child_frame_id) for t in tf] == \
        [(frame, "r1/camera"), ("map", frame + "x")]
    np.testing.assert_allclose(_message_T(tf[1].transform), U, atol=1e-12)
    path = store.deserialize_cdr(made[cdr.PATH], cdr.PATH)
    assert [_stamp_ns(p.header) for p in path.poses] == [stamp - 7, stamp]
    status = store.deserialize_cdr(made[cdr.DIAGNOSTIC_ARRAY], cdr.DIAGNOSTIC_ARRAY).status
    assert status[0].level == cdr.WARN and status[0].values[1].value == "12"


def test_an_empty_path_and_the_type_hashes():
    store = _typestore()
    data = cdr.path(5, "r1/map", [], np.zeros((0, 4, 4)))
    assert store.deserialize_cdr(data, cdr.PATH).poses == []
    for ros_type, type_hash in cdr.TYPE_HASHES.items():
        assert store.hash_rihs01(ros_type) == type_hash


def test_stamps_round_to_the_nanosecond():
    # float64 holds an epoch time to ~0.24 us: a TUM stamp (us) comes back to its us.
    assert round(cdr.stamp_ns(1305031229.528748) / 1000) == 1305031229528748
    assert cdr.stamp_ns(0.5) == 500_000_000


def test_attachment_round_trip():
    gid = bytes(range(16))
    parsed = parse_attachment(make_attachment(7, 1_700_000_000_000_000_000, gid))
    assert (parsed.sequence_number, parsed.source_timestamp_ns, parsed.gid) == \
        (7, 1_700_000_000_000_000_000, gid)
    with pytest.raises(ValueError, match="16 bytes"):
        make_attachment(1, 1, b"short")


# ---------------------------------------------------------------------------- the node


def sdk_subscriber(endpoint: str, topic: str, ros_type: str, sink: list,
                   transient_local: bool = False):
    """zenoh-ros2-sdk's subscriber, with the definition and hash from rosbags (offline)."""
    from zenoh_ros2_sdk.qos import QosDurability, QosProfile
    from zenoh_ros2_sdk.subscriber import ROS2Subscriber

    store = _typestore()
    qos = QosProfile(durability=QosDurability.TRANSIENT_LOCAL, history_depth=1) \
        if transient_local else None
    return ROS2Subscriber(topic, ros_type, sink.append,
                          msg_definition=store.generate_msgdef(ros_type, 2)[0],
                          type_hash=store.hash_rihs01(ros_type), router_ip="127.0.0.1",
                          router_port=int(endpoint.rsplit(":", 1)[1]), qos=qos)


def test_a_node_announces_itself_and_its_publishers_as_rmw_zenoh_does(ros_router):
    from fleetslam.datasets.ros2_session import open_ros_session
    from fleetslam.ros2_out.node import RosNode

    session = open_ros_session(ros_router, 5.0)
    try:
        node = RosNode(session, "fleetslam_r1", domain_id=3)
        pub = node.publisher("/r1/pose", cdr.POSE_STAMPED, 10)
        node.publisher("/tf_static", cdr.TF_MESSAGE, 1, transient_local=True)
        assert key_topic(pub.key) == "/r1/pose" and key_type(pub.key) == cdr.POSE_STAMPED
        assert pub.key.startswith("3/r1/pose/geometry_msgs::msg::dds_::PoseStamped_/RIHS01_")
        tokens = [str(r.ok.key_expr) for r in
                  session.liveliness().get("@ros2_lv/3/**", timeout=2.0) if r.ok]
        zid = str(session.info.zid())
        assert f"@ros2_lv/3/{zid}/0/0/NN/%/%/fleetslam_r1" in tokens
        endpoints = {e.topic: e for e in map(parse_liveliness, tokens) if e is not None}
        assert endpoints["/r1/pose"].kind == "MP" and \
            endpoints["/r1/pose"].node == "/fleetslam_r1"
        assert endpoints["/tf_static"].ros_type == cdr.TF_MESSAGE
        qos = {t.split("/")[9]: t.split("/")[12] for t in tokens if "/MP/" in t}
        assert qos == {"%r1%pose": "::,10:,:,:,,", "%tf_static": ":1:,1:,:,:,,"}
        node.close()
        humble = RosNode(session, "fleetslam_r2", humble=True)
        assert humble.publisher("/r2/pose", cdr.POSE_STAMPED, 10).key == \
            "0/r2/pose/geometry_msgs::msg::dds_::PoseStamped_/TypeHashNotSupported"
        humble.close()
    finally:
        session.close()


def test_a_late_subscriber_gets_the_transient_local_message(sdk_session):
    """Published before anyone listens: zenoh-ros2-sdk's TRANSIENT_LOCAL subscriber (on a
    one-chunk topic: the SDK looks late publishers up unmangled) and zenoh-ext's
    AdvancedSubscriber with late-publisher detection (on a namespaced topic) get it."""
    import zenoh.ext

    from fleetslam.datasets.ros2_session import open_ros_session
    from fleetslam.ros2_out.node import RosNode

    session = open_ros_session(sdk_session, 5.0)
    T = _pose(3)
    try:
        node = RosNode(session, "fleetslam_r1")
        node.publisher("/tf_static", cdr.TF_MESSAGE, 1, transient_local=True).publish(
            cdr.tf_message([(10, "map", "r1/map", T)]))
        latched = node.publisher("/r1/latched", cdr.POSE_STAMPED, 1, transient_local=True)
        latched.publish(cdr.pose_stamped(11, "r1/map", T))
        time.sleep(0.3)
        got: list = []
        sub = sdk_subscriber(sdk_session, "/tf_static", cdr.TF_MESSAGE, got, transient_local=True)
        wait_for(lambda: got, 5.0, "the SDK's late subscriber")
        np.testing.assert_allclose(_message_T(got[0].transforms[0].transform), T, atol=1e-12)
        sub.close()
        late: list = []
        ext = zenoh.ext.declare_advanced_subscriber(
            session, latched.key, lambda s: late.append(s.payload.to_bytes()),
            history=zenoh.ext.HistoryConfig(detect_late_publishers=True))
        wait_for(lambda: late, 5.0, "zenoh-ext's late AdvancedSubscriber")
        assert late[0] == cdr.pose_stamped(11, "r1/map", T)
        ext.undeclare()
        node.close()
    finally:
        session.close()


# ---------------------------------------------------------------------------- placements


def test_a_placement_is_checked_before_it_is_used():
    T = _pose(4)
    message = json.loads(protocol.encode(protocol.Placed("r2", T, False)))
    placed = protocol.parse_placed(message)
    assert placed.group == "r2" and not placed.final
    np.testing.assert_array_equal(placed.T_global_map, T)  # JSON carries float64 exactly
    bad = {
        "group": ({**message, "group": "r/2"}, "group 'r/2' is not a robot id"),
        "final": ({**message, "final": "yes"}, "final must be true or false"),
        "shape": ({**message, "T_global_map": [[1, 0, 0]] * 4}, "4 rows of 4 numbers"),
        "text": ({**message, "T_global_map": "eye"}, "4 rows of 4 numbers"),
        "nan": ({**message, "T_global_map": [[float("nan")] * 4] * 4}, "not finite"),
        "huge": ({**message, "T_global_map": [[10**400] * 4] * 4}, "not finite"),
        "scaled": ({**message, "T_global_map": (2 * np.eye(4)).tolist()}, "not a rigid"),
        "mirrored": ({**message, "T_global_map": np.diag([1.0, 1, -1, 1]).tolist()},
                     "not a rigid"),
        "row": ({**message, "T_global_map": np.vstack([T[:3], [0, 0, 1, 1]]).tolist()},
                "not a rigid"),
    }
    for name, (m, reason) in bad.items():
        with pytest.raises(ValueError, match=reason):
            protocol.parse_placed(m)


def test_robots_hear_new_moved_and_final_placements_and_again_later():
    from fleetslam.cloud.merge.fleet_frames import FleetFrames
    from fleetslam.config import MergeConfig

    sent: list[tuple[str, dict]] = []
    cfg = MergeConfig(placement_resend_s=0.05)
    frames = FleetFrames(cfg, lambda key, data: sent.append((key, json.loads(data))))
    T = _pose(5)
    assert frames.update({"r1": ("r0", T), "r0": ("r0", np.eye(4))}) == 2
    nudge = T @ make_T(np.eye(3), [0.001, 0, 0])  # below placement_move_m
    assert frames.update({"r1": ("r0", nudge)}) == 0
    moved = T @ make_T(np.eye(3), [0.05, 0, 0])
    assert frames.update({"r1": ("r0", moved)}) == 1
    refined = moved @ make_T(np.eye(3), [0.04, 0, 0])  # FS-HICP moved it from the graph's
    assert frames.update({"r1": ("r0", refined)}, final=True) == 1
    # The graph has not moved since: the merge's stays, though it differs from the graph's.
    assert frames.update({"r1": ("r0", moved)}) == 0
    assert frames.update({"r1": ("r0", moved @ make_T(np.eye(3), [0.001, 0, 0]))}) == 0
    assert [k for k, _ in sent] == ["fleet/r0/reply", "fleet/r1/reply", "fleet/r1/reply",
                                    "fleet/r1/reply"]
    assert sent[-1][1]["final"] is True
    time.sleep(0.06)
    frames.resend_due()
    assert {k for k, _ in sent[4:]} == {"fleet/r0/reply", "fleet/r1/reply"}
    # The graph moves on (new keyframes after the merge): the live placement replaces it.
    assert frames.update({"r1": ("r0", moved @ make_T(np.eye(3), [0.05, 0, 0]))}) == 1


def _reply(robot, message: dict | bytes) -> None:
    data = message if isinstance(message, bytes) else json.dumps(message).encode()
    robot.replies.take(data)


def test_a_malformed_placement_is_said_in_one_line_and_the_robot_goes_on(tmp_path_factory,
                                                                         caplog):
    from conftest import small_scene

    from fleetslam.datasets.tum import RgbdSequence
    from fleetslam.edge.robot import Robot

    folder = small_scene(tmp_path_factory, 2)[0]
    robot = Robot("r1", RgbdSequence(folder), str(folder), 3, Config(), show_progress=False)
    caplog.set_level(logging.WARNING, logger="fleetslam.robot")
    _reply(robot, {"type": "placed", "group": "r0", "final": False,
                   "T_global_map": [[1, 0, 0, 0]] * 4})
    lines = [r.getMessage() for r in caplog.records]
    assert lines == ["robot r1: placement from the cloud rejected: placed: T_global_map is "
                     "not a rigid transform (a rotation and a translation, last row 0 0 0 1)"]
    assert robot.report.placed is None and robot.report.placed_rejected == 1
    T = _pose(6)
    _reply(robot, protocol.encode(protocol.Placed("r0", T, True)))
    assert robot.report.placed["group"] == "r0" and robot.report.placed["final"]
    np.testing.assert_array_equal(robot.report.placed["T_global_map"], T)


def test_an_unreachable_ros2_router_is_said_once_and_tracking_goes_on(caplog):
    from fleetslam.edge.report import RobotReport
    from fleetslam.edge.ros2_out import RobotRosOut
    from fleetslam.launch import free_endpoint
    from fleetslam.wire.messages import Feedback

    config = Config().with_values({"ros2_out.endpoint": free_endpoint(),
                                   "ros2_out.connect_timeout_s": 0.3})
    out = RobotRosOut("r1", config.ros2_out, RobotReport("r1", 3)).start()
    caplog.set_level(logging.WARNING, logger="fleetslam.ros2_out")
    try:
        wait_for(lambda: caplog.records, 10.0, "the unreachable router's message")
        for i in range(5):
            out.feedback(Feedback(i, 1.0 + i, True, False, 100, _pose(i), 5.0), 0.03)
        out.publish_status()
        assert out.tracked_frames == 5 and out.unpublished == 11  # 5 poses, 5 TF, a status
    finally:
        out.close()
    messages = [r.getMessage() for r in caplog.records]
    assert len(messages) == 1 and "no ROS 2 Zenoh router answers at" in messages[0] and \
        "robot r1 goes on without it" in messages[0] and "\n" not in messages[0] and \
        ".rs:" not in messages[0]


# ---------------------------------------------------------------------------- end to end


def _tum_rows(path) -> dict[int, np.ndarray]:
    """A TUM file's rows by their stamp in microseconds."""
    rows = np.loadtxt(path, comments="#", ndmin=2)
    return {int(round(r[0] * 1e6)): r[1:] for r in rows}


def run_through_cloud(tmp_path, robots: list, merge: bool = False,
                      cloud_config: Config | None = None, while_up=None,
                      view=None) -> dict | None:
    """Run ``robots`` (edge.robot.Robot, their config's endpoint a cloud to start here) to
    their end in threads; with ``merge``, merge once every robot's session ended (a robot
    holding its ROS 2 node then hears the final placement); the summary, else None.
    ``while_up(summary)`` runs before the cloud closes."""
    from fleetslam.cloud.server import CloudServer

    endpoint = robots[0].endpoint
    server = CloudServer(cloud_config or Config(), tmp_path / "cloud", endpoint,
                         view=view).start()
    errors: list = []

    def run(robot) -> None:
        try:
            robot.run()
        except BaseException as exc:  # noqa: BLE001 - reported by the test
            errors.append(exc)

    threads = [threading.Thread(target=run, args=(r,), daemon=True) for r in robots]
    summary = None
    try:
        for t in threads:
            t.start()
        wait_for(lambda: all(server.sessions.get(r.robot_id) is not None
                             and server.sessions[r.robot_id].finished is not None
                             for r in robots) or errors, 300, "the robots' sessions to end")
        if merge:
            summary = server.merge()
        for t in threads:
            t.join(60)
        assert not errors and not any(t.is_alive() for t in threads), errors
        if while_up is not None:
            while_up(summary)
    finally:
        server.close()
    return summary


def ros_robot(robot_id: str, spec: str, cloud: str, ros_router: str | None = None, **ros2_out):
    from fleetslam.datasets.recording import open_source
    from fleetslam.edge.robot import Robot

    if ros_router is not None:
        ros2_out = {"endpoint": ros_router, **ros2_out}
    config = Config().with_values({"transport.endpoint": cloud,
                                   **{f"ros2_out.{k}": v for k, v in ros2_out.items()}})
    return Robot(robot_id, open_source(spec), robot_id, 3, config, show_progress=False)


@pytest.mark.realdata
def test_the_robots_pose_tf_and_fleet_frame_reach_ros2(sdk_session, tmp_path):
    """Two robots on real frames (TUM fr1_rpy 0-89 and 50-149) through a cloud; r1
    publishes to a ROS 2 graph (a router standing in for rmw_zenohd). Subscribers we did
    not write get /r1/pose for >= 95 % of r1's tracked frames, each the pose the cloud
    tracked (online.tum) to 1e-9, /tf the same, and after the merge /tf_static's map ->
    r1/map is summary.json's T_global_map."""
    from fleetslam.launch import free_endpoint

    require(TUM_RPY)
    poses: list = []
    tfs: list = []
    static: list = []
    paths: list = []
    status: list = []
    subs = [sdk_subscriber(sdk_session, "/r1/path", cdr.PATH, paths),
            sdk_subscriber(sdk_session, "/diagnostics", cdr.DIAGNOSTIC_ARRAY, status),
            sdk_subscriber(sdk_session, "/r1/pose", cdr.POSE_STAMPED, poses),
            sdk_subscriber(sdk_session, "/tf", cdr.TF_MESSAGE, tfs),
            sdk_subscriber(sdk_session, "/tf_static", cdr.TF_MESSAGE, static, transient_local=True)]
    cloud = free_endpoint()
    r1 = ros_robot("r1", f"{TUM_RPY}:0-89", cloud, sdk_session, hold_s=120.0)
    try:
        summary = run_through_cloud(tmp_path, [r1, ros_robot("r2", f"{TUM_RPY}:50-149", cloud)],
                                    merge=True)
        final = summary["merge"].get("T_global_map", {}).get("r1")
        # The robot published it before it ended; on a loaded machine it may still be on its
        # way to our subscriber.
        wait_for(lambda: final is None or any(
            t.child_frame_id == "r1/map" and np.allclose(_message_T(t.transform), final,
                                                         atol=1e-9)
            for m in list(static) for t in m.transforms), 10.0,
                 "the merge's map -> r1/map on /tf_static")
    finally:
        for sub in subs:
            sub.close()
    online = _tum_rows(tmp_path / "cloud" / "r1" / "online.tum")
    assert len(online) >= 80  # r1 tracked nearly all of its 90 frames
    by_stamp = {int(round(_stamp_ns(p.header) / 1000)): p for p in poses}
    assert len(set(by_stamp) & set(online)) >= 0.95 * len(online)
    assert set(by_stamp) <= set(online)  # nothing published for a frame not tracked
    for stamp, p in by_stamp.items():
        assert p.header.frame_id == "r1/map"
        got = tum_from_T(_message_T(p.pose)[None])[0]
        np.testing.assert_allclose(got, online[stamp], atol=1e-9)
    camera_tf = [t for m in tfs for t in m.transforms if t.child_frame_id == "r1/camera"]
    # Like rmw_zenoh's volatile publishers, ours drop rather than block when the link is
    # congested: a loaded machine may lose one (seen: 89 of 90 once).
    assert len(camera_tf) >= 0.95 * len(online)
    for t in camera_tf:
        assert t.header.frame_id == "r1/map"
        np.testing.assert_allclose(tum_from_T(_message_T(t.transform)[None])[0],
                                   online[int(round(_stamp_ns(t.header) / 1000))], atol=1e-9)
    merge = summary["merge"]
    assert sorted(merge["members"]) == ["r1", "r2"], "the two robots did not join"
    fleet = [t for m in static for t in m.transforms if t.child_frame_id == "r1/map"]
    assert fleet and all(t.header.frame_id == "map" for t in fleet)
    np.testing.assert_allclose(_message_T(fleet[-1].transform),
                               np.array(merge["T_global_map"]["r1"]), atol=1e-9)
    assert r1.report.placed["final"] and r1.report.ros2_poses >= 0.95 * len(online)
    # The path: the tracked poses so far, in r1/map; the status: tracking, in the group.
    assert paths and paths[-1].header.frame_id == "r1/map"
    for p in paths[-1].poses:
        np.testing.assert_allclose(tum_from_T(_message_T(p.pose)[None])[0],
                                   online[int(round(_stamp_ns(p.header) / 1000))], atol=1e-9)
    last = {v.key: v.value for v in status[-1].status[0].values}
    assert status[-1].status[0].hardware_id == "r1" and last["state"] in ("tracking",
                                                                         "relocalised")
    assert last["fleet_group"] in ("r1", "r2") and float(last["round_trip_ms_median"]) > 0


def _transform_message(store, stamp_ns: int, parent: str, child: str, T: np.ndarray):
    t = store.types
    v = tum_from_T(T[None])[0]
    return t["geometry_msgs/msg/TransformStamped"](
        header=t["std_msgs/msg/Header"](
            stamp=t["builtin_interfaces/msg/Time"](sec=stamp_ns // 1_000_000_000,
                                                   nanosec=stamp_ns % 1_000_000_000),
            frame_id=parent),
        child_frame_id=child,
        transform=t["geometry_msgs/msg/Transform"](
            translation=t["geometry_msgs/msg/Vector3"](x=v[0], y=v[1], z=v[2]),
            rotation=t["geometry_msgs/msg/Quaternion"](x=v[3], y=v[4], z=v[5], w=v[6])))


@pytest.mark.realdata
def test_with_odometry_the_robot_publishes_map_to_odom(sdk_session, tmp_path):
    """REP 105: the robot's graph has odometry (odom -> base_link on /tf, from zenoh-ros2-
    sdk_session) and the camera's mounting (static base_link -> camera): the robot publishes
    r1/map -> odom, never a second parent for the camera, and map -> odom composed with the
    robot's own odom -> camera at the frame's stamp is the pose the cloud tracked."""
    from zenoh_ros2_sdk.publisher import ROS2Publisher

    from fleetslam.datasets.recording import open_source
    from fleetslam.launch import free_endpoint

    require(TUM_RPY)
    store = _typestore()
    stamps = [cdr.stamp_ns(t) for t in open_source(f"{TUM_RPY}:0-59").timestamps]
    odom = {t: make_T(rotation_exp([0.0, 0.0, 0.002 * i]), [0.01 * i, 0.003 * i, 0.0])
            for i, t in enumerate(stamps)}
    mount = make_T(rotation_exp([-np.pi / 2, 0.0, -np.pi / 2]), [0.1, 0.0, 0.3])
    camera = "camera_rgb_optical_frame"
    port = int(sdk_session.rsplit(":", 1)[1])
    pubs = {name: ROS2Publisher(name, cdr.TF_MESSAGE,
                                msg_definition=store.generate_msgdef(cdr.TF_MESSAGE, 2)[0],
                                type_hash=store.hash_rihs01(cdr.TF_MESSAGE),
                                node_name="robot_base", router_ip="127.0.0.1", router_port=port)
            for name in ("/tf", "/tf_static")}
    stop = threading.Event()

    def base_node() -> None:
        # zenoh-ros2-sdk keeps no transient-local cache: the static mounting is sent again,
        # as is the odometry, so a robot that starts later hears both.
        while not stop.wait(0.1):
            pubs["/tf_static"].publish(transforms=[_transform_message(
                store, stamps[0], "base_link", camera, mount)])
            pubs["/tf"].publish(transforms=[_transform_message(store, t, "odom", "base_link",
                                                               T) for t, T in odom.items()])

    tfs: list = []
    sub = sdk_subscriber(sdk_session, "/tf", cdr.TF_MESSAGE, tfs)
    node = threading.Thread(target=base_node, daemon=True)
    node.start()
    r1 = ros_robot("r1", f"{TUM_RPY}:0-59", free_endpoint(), sdk_session, camera_frame=camera)
    try:
        run_through_cloud(tmp_path, [r1])
    finally:
        stop.set()
        node.join(5)
        sub.close()
    online = _tum_rows(tmp_path / "cloud" / "r1" / "online.tum")
    ours = [t for m in tfs for t in m.transforms if t.header.frame_id == "r1/map"]
    to_odom = [t for t in ours if t.child_frame_id == "odom"]
    assert len(to_odom) >= 0.8 * len(online), (len(to_odom), len(online))
    assert {t.child_frame_id for t in ours} <= {"odom", camera}  # before odometry was heard
    for t in to_odom:
        stamp = _stamp_ns(t.header)
        T_map_camera = _message_T(t.transform) @ odom[stamp] @ mount
        np.testing.assert_allclose(tum_from_T(T_map_camera[None])[0],
                                   online[int(round(stamp / 1000))], atol=1e-9)
    assert r1.report.ros2_unpublished == 0


def test_the_tf_tree_interpolates_and_says_what_is_missing():
    from fleetslam.ros2_out.tf_buffer import TfBuffer, TfError
    from fleetslam.transforms import rotation_angle_deg

    tree = TfBuffer(keep_s=10.0)
    A = make_T(rotation_exp([0, 0, 0.2]), [1.0, 0, 0])
    B = make_T(rotation_exp([0, 0, 0.6]), [3.0, 0, 0])
    mount = _pose(7)
    tree.add([(1_000, "odom", "base_link", A), (3_000, "odom", "base_link", B)], static=False)
    tree.add([(0, "base_link", "cam", mount)], static=True)
    assert tree.root("cam") == "odom" and tree.parent("odom") is None
    half = tree.lookup("odom", "cam", 2_000) @ invert_T(mount)
    np.testing.assert_allclose(half[:3, 3], [2.0, 0, 0], atol=1e-12)
    assert abs(rotation_angle_deg(half[:3, :3]) - np.degrees(0.4)) < 1e-9
    np.testing.assert_allclose(tree.lookup("cam", "odom", 1_000), invert_T(A @ mount),
                               atol=1e-12)
    with pytest.raises(TfError, match=r"odom -> base_link at 0.000 s: the buffer holds "
                                      r"0.000-0.000 s"):
        tree.lookup("odom", "cam", 5_000)
    tree.add([(0, "other", "thing", A)], static=True)
    with pytest.raises(TfError, match="no TF path from thing to cam: cam's tree ends at odom, "
                                      "thing's at other"):
        tree.lookup("thing", "cam", 2_000)
    tree.add([(0, "cam", "odom", A)], static=True)
    with pytest.raises(TfError, match="the TF tree has a loop: cam -> odom -> base_link -> cam"):
        tree.lookup("odom", "cam", 2_000)
    # Old dynamic transforms leave the buffer.
    tree = TfBuffer(keep_s=1.0)
    tree.add([(i * 500_000_000, "odom", "base", A) for i in range(10)], static=False)
    with pytest.raises(TfError, match="the buffer holds 3.500-4.500 s"):
        tree.lookup("odom", "base", 0)


def test_a_tf_message_that_is_not_one_is_refused_with_the_reason():
    good = cdr.tf_message([(5, "odom", "base_link", _pose(8))])
    assert cdr.read_tf_message(good, "/tf")[0][1:3] == ("odom", "base_link")
    np.testing.assert_allclose(cdr.read_tf_message(good, "/tf")[0][3], _pose(8), atol=1e-12)
    cases = {
        "truncated": (good[:-3], "ends at byte"),
        "not cdr": (b"\x07" + good[1:], "not classic CDR"),
        "many": (good[:4] + (10**6).to_bytes(4, "little") + good[8:], "1000000 transforms"),
        "same frame": (cdr.tf_message([(5, "odom", "odom", np.eye(4))]), "does not name two"),
        "empty": (bytes(cdr.CdrWriter().buf), "ends at byte"),
    }
    bad_q = bytearray(good)
    bad_q[-8:] = struct.pack("<d", 3.0)  # w of the quaternion
    cases["quaternion"] = (bytes(bad_q), "not finite with a unit quaternion")
    for name, (data, reason) in cases.items():
        with pytest.raises(cdr.CdrError, match=reason):
            cdr.read_tf_message(data, "/tf")


def test_the_cloud_publishes_poses_and_each_merges_maps_for_late_subscribers(
        sdk_session, tmp_path, synthetic_scene):
    """``cloud --ros2-out``: each robot's pose as the cloud tracks it (zenoh-ros2-sdk's
    subscriber: every tracked frame, at its capture time, the pose of online.tum), and after
    the merge, for a subscriber that starts only then (zenoh-ext's AdvancedSubscriber
    looking for late publishers, as rmw_zenoh's TRANSIENT_LOCAL subscriptions do),
    /map/global and /map/grid: the merge's PLY and nav2 map."""
    import zenoh.ext

    from fleetslam.datasets.rmw_zenoh import topic_key
    from fleetslam.datasets.ros2_session import open_ros_session
    from fleetslam.io.ply import read_ply
    from fleetslam.launch import free_endpoint
    from fleetslam.visualisation.views import open_view

    _, folders = synthetic_scene
    cloud = free_endpoint()
    config = Config().with_values({"ros2_out.endpoint": sdk_session})
    view = open_view(config, None, False)
    assert view.sink.wait_connected(10.0)
    robots = [ros_robot(f"r{i}", str(f), cloud) for i, f in enumerate(folders)]
    got: dict[str, list] = {"/map/global": [], "/map/grid": [], "/r1/global_path": []}
    poses: list = []
    live = sdk_subscriber(sdk_session, "/r0/pose", cdr.POSE_STAMPED, poses)

    static: list = []

    def subscribe_late(_) -> None:
        late_tf = sdk_subscriber(sdk_session, "/tf_static", cdr.TF_MESSAGE, static,
                                 transient_local=True)
        wait_for(lambda: static, 10.0, "the merge's /tf_static")
        late_tf.close()
        session = open_ros_session(sdk_session, 5.0)
        try:
            subs = [zenoh.ext.declare_advanced_subscriber(
                session, topic_key(0, topic), lambda s, t=topic: got[t].append(s),
                history=zenoh.ext.HistoryConfig(detect_late_publishers=True))
                for topic in got]
            wait_for(lambda: all(got.values()), 10.0, "the merge's latched maps")
            for sub in subs:
                sub.undeclare()
        finally:
            session.close()

    try:
        summary = run_through_cloud(tmp_path, robots, merge=True, cloud_config=config,
                                    while_up=subscribe_late, view=view)
    finally:
        live.close()
    merge = summary["merge"]
    assert sorted(merge["members"]) == ["r0", "r1"]
    online = _tum_rows(tmp_path / "cloud" / "r0" / "online.tum")
    by_stamp = {int(round(_stamp_ns(p.header) / 1000)): p for p in poses}
    assert set(by_stamp) == set(online)  # every tracked frame, at its capture time
    for stamp, p in by_stamp.items():
        np.testing.assert_allclose(tum_from_T(_message_T(p.pose)[None])[0], online[stamp],
                                   atol=1e-9)
    fleet = {t.child_frame_id: t for t in static[-1].transforms}
    assert set(fleet) == {"r0/map", "r1/map"}
    for robot, t in fleet.items():
        assert t.header.frame_id == "map"
        np.testing.assert_allclose(_message_T(t.transform),
                                   np.array(merge["T_global_map"][robot.split("/")[0]]),
                                   atol=1e-9)
    store = _typestore()
    cloud_msg = store.deserialize_cdr(got["/map/global"][-1].payload.to_bytes(),
                                      "sensor_msgs/msg/PointCloud2")
    points, _ = read_ply(tmp_path / "cloud" / merge["global_map"])
    assert cloud_msg.header.frame_id == "map" and cloud_msg.width == len(points) > 1000
    xyz = np.frombuffer(cloud_msg.data.tobytes(), np.float32).reshape(-1, 4)[:, :3]
    np.testing.assert_allclose(xyz, points, atol=1e-5)
    grid = store.deserialize_cdr(got["/map/grid"][-1].payload.to_bytes(),
                                 "nav_msgs/msg/OccupancyGrid")
    assert [grid.info.width, grid.info.height] == merge["grid"]["size"]
    cells = np.asarray(grid.data).reshape(grid.info.height, grid.info.width)
    assert (cells == 100).sum() == merge["grid"]["occupied_cells"]
    assert (cells == 0).sum() == merge["grid"]["free_cells"]
    assert abs(grid.info.resolution - merge["grid"]["resolution_m"]) < 1e-9
    path = store.deserialize_cdr(got["/r1/global_path"][-1].payload.to_bytes(),
                                 "nav_msgs/msg/Path")
    assert path.header.frame_id == "map" and len(path.poses) == 30


def test_a_tf_tree_with_a_loop_or_a_gap_costs_the_tf_not_the_pose(caplog):
    """The robot's own TF with a loop, then one whose camera chain stops short of the
    stamp: each said once in one line, the pose goes on being published (counted), and a
    tree that mends is said too."""
    from fleetslam.edge.report import RobotReport
    from fleetslam.edge.ros2_out import RobotRosOut
    from fleetslam.launch import free_endpoint
    from fleetslam.wire.messages import Feedback

    nobody = free_endpoint()  # nothing is sent anyway
    config = Config().with_values({"ros2_out.endpoint": nobody})
    out = RobotRosOut("r1", config.ros2_out, RobotReport("r1", 3))
    caplog.set_level(logging.INFO, logger="fleetslam.ros2_out")
    out.tf.add([(0, "base_link", "r1/camera", _pose(1)), (0, "r1/camera", "odom", _pose(2))],
               static=True)
    out.tf.add([(0, "odom", "base_link", _pose(3))], static=False)
    for i in range(3):
        out.feedback(Feedback(i, 1.0 + i, True, False, 100, _pose(i), 5.0), None)
    assert out.tracked_frames == 3 and out.tf_skipped == 3
    out.tf.add([(0, "base_link", "r1/camera", _pose(1))], static=True)
    out.tf.add([(cdr.stamp_ns(1.0), "odom", "r1_base", _pose(3))], static=False)  # unrelated
    out.tf.add([(0, "world", "odom", np.eye(4))], static=True)  # odom's parent: the loop is gone
    out.feedback(Feedback(3, 4.0, True, False, 100, _pose(3), 5.0), None)
    out.tf.add([(cdr.stamp_ns(5.0), "odom", "base_link", _pose(4))], static=False)
    out.feedback(Feedback(4, 5.0, True, False, 100, _pose(4), 5.0), None)
    lines = [r.getMessage() for r in caplog.records]
    assert lines[0] == ("robot r1: ROS 2 out: no /tf for this frame (the pose goes on): the "
                        "TF tree has a loop: r1/camera -> odom -> base_link -> r1/camera")
    assert lines[-1] == "robot r1: ROS 2 out: /tf placed again (r1/map -> world)"
    assert len(lines) == 2 and all("\n" not in line for line in lines)
    assert out.tracked_frames == 5 and out.tf_skipped == 4


@pytest.mark.realdata
def test_robot_and_cloud_processes_publish_with_the_flag(ros_router, tmp_path):
    """``fleetslam cloud --ros2-out`` and ``fleetslam robot --ros2-out`` as processes, onto
    one graph: the cloud's node announces itself, and both publish /r1/pose for (nearly)
    every tracked frame (the flag once reached the cloud after its views were made)."""
    from fleetslam.datasets.rmw_zenoh import topic_key
    from fleetslam.launch import free_endpoint, start_cloud, start_robot, stop
    from fleetslam.transport.zenoh_session import open_connecting

    require(TUM_RPY)
    session = open_connecting(ros_router, 10.0)
    got: list = []
    sub = session.declare_subscriber(topic_key(0, "/r1/pose"), got.append)
    nodes: set[str] = set()
    cloud_endpoint = free_endpoint()
    cloud = start_cloud(cloud_endpoint, tmp_path / "cloud", tmp_path / "cloud.log",
                        extra=["--ros2-out", ros_router])
    try:
        robot = start_robot(cloud_endpoint, "r1", f"{TUM_RPY}:0-29", 3, tmp_path / "r1.log",
                            extra=["--ros2-out", ros_router])
        wait_for(lambda: robot.poll() is not None, 120, "the robot process")
        assert robot.returncode == 0, (tmp_path / "r1.log").read_text()
        nodes = {str(r.ok.key_expr).split("/")[-1] for r in
                 session.liveliness().get("@ros2_lv/0/*/*/*/NN/**", timeout=2.0) if r.ok}
    finally:
        stop(cloud)
        sub.undeclare()
        session.close()
    assert any(n.startswith("fleetslam_cloud_") for n in nodes), nodes
    online = _tum_rows(tmp_path / "cloud" / "r1" / "online.tum")
    stamps = []
    for sample in got:
        sec, nanosec = cdr.CdrReader(sample.payload.to_bytes(), "/r1/pose").unpack("iI")
        stamps.append(sec * 1_000_000 + int(round(nanosec / 1000)))
    assert len(stamps) >= 2 * 0.95 * len(online)  # the robot's and the cloud's
    assert set(stamps) <= set(online)

"""What a robot publishes on its own ROS 2 graph while it runs (``fleetslam robot
--ros2-out ENDPOINT``), as a node named ``fleetslam_<robot>``:

    /<robot>/pose   geometry_msgs/PoseStamped  every tracked frame, stamped with its capture
                                               time, in <robot>/map; sent the moment the
                                               cloud's feedback arrives
    /tf             tf2_msgs/TFMessage         <robot>/map -> the camera, with each pose;
                                               where the robot's own TF already gives the
                                               camera a parent (odom -> base_link -> camera),
                                               <robot>/map -> the top of that tree instead
                                               (REP 105's map -> odom), from the TF heard at
                                               the frame's stamp
    /tf_static      tf2_msgs/TFMessage         map -> <robot>/map once the cloud placed the
                                               robot's map in a group (transient local,
                                               re-sent whenever the cloud moves it)
    /<robot>/path   nav_msgs/Path              the tracked poses, every path_every_s
    /diagnostics    diagnostic_msgs/DiagnosticArray  tracking / lost / relocalised, the
                                               link's round trip, frames skipped

The router may be down or start later: the node connects in the background (said once,
then tried again every ``retry_s``) and tracking never waits for it; what could not be
published is counted. Every call is cheap and thread-safe (Zenoh's callback threads).
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from dataclasses import dataclass

import numpy as np
import zenoh
import zenoh.ext

from fleetslam.config import Ros2OutConfig
from fleetslam.datasets.live import LiveSource
from fleetslam.datasets.rmw_zenoh import dds_type_name, parse_attachment, topic_key
from fleetslam.datasets.source import RecordedSource
from fleetslam.edge.report import RobotReport
from fleetslam.ros2_out import cdr
from fleetslam.ros2_out.graph import GraphLink
from fleetslam.ros2_out.node import RosNode, RosPublisher
from fleetslam.ros2_out.tf_buffer import TfBuffer, TfError
from fleetslam.transforms import invert
from fleetslam.transport.protocol import Placed
from fleetslam.wire.messages import Feedback

log = logging.getLogger("fleetslam.ros2_out")

# Keep-last depths, as ROS 2's own publishers of these topics use them (tf2's broadcaster
# 100, its static broadcaster 1 transient local).
POSE_DEPTH = 10
TF_DEPTH = 100
PATH_DEPTH = 1
DIAGNOSTICS_DEPTH = 10
# Round trips the status's median is taken over.
ROUND_TRIPS_KEPT = 100
# Per-frame timings kept for the report (bench/ros2_out.py): the newest.
TIMINGS_KEPT = 20_000


def ros_token(name: str) -> str:
    """A robot id as a ROS name token: ROS names allow no '-' and no leading digit."""
    token = name.replace("-", "_")
    return "_" + token if token[:1].isdigit() else token


@dataclass
class PoseTiming:
    """One published pose: when the robot took its frame, handed it to the link (coded), heard
    its feedback and put its pose (time.time_ns(): a subscriber in another process on this
    machine compares them)."""

    frame_index: int
    taken_ns: int | None
    sent_ns: int | None
    feedback_ns: int
    published_ns: int


class RobotRosOut:
    def __init__(self, robot_id: str, cfg: Ros2OutConfig, report: RobotReport,
                 source: RecordedSource | LiveSource | None = None) -> None:
        """``source``: the robot's frames (its skipped frames; a ROS source's image
        frame_id names the camera's TF frame)."""
        self.robot_id = robot_id
        self.cfg = cfg
        self.report = report
        self.source = source
        self.live = source if isinstance(source, LiveSource) else None
        name = ros_token(robot_id)
        self.topics = {"pose": f"/{name}/pose", "path": f"/{name}/path"}
        self.map_frame = f"{robot_id}/map"
        self.fleet_frame = cfg.fleet_frame.strip("/")
        self.node_name = f"fleetslam_{name}"
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self.graph = GraphLink(cfg, self.node_name, self, f"robot {robot_id}",
                               hint="Set it with --ros2-out or [ros2_out] endpoint")
        self._pubs: dict[str, RosPublisher] = {}
        self._subs: list = []
        # The robot's own TF tree, as its graph publishes it (not ours: by publisher GID).
        self.tf = TfBuffer(cfg.tf_buffer_s)
        self.tf_rejected = 0  # /tf messages that were not TFMessages (said once)
        self.tf_skipped = 0  # frames whose TF could not be placed in the robot's tree
        self._tf_problem: str | None = None  # the one said last, until it mends
        # The tracked poses (online, as the feedback gave them), for the path.
        self._stamps: deque[int] = deque(maxlen=cfg.path_max_poses)
        self._poses: deque[np.ndarray] = deque(maxlen=cfg.path_max_poses)
        self._path_sent = 0  # tracked_frames when the path was last sent: unchanged since?
        self._placed: Placed | None = None
        self.state = "waiting"  # waiting, tracking, lost, relocalised
        self.tracked_frames = 0
        self.lost_frames = 0
        self.unpublished = 0  # messages dropped while no router was reachable
        self._round_trips: deque[float] = deque(maxlen=ROUND_TRIPS_KEPT)
        self._taken: dict[int, list[int | None]] = {}  # frame -> [taken, sent] ns
        self.timings: deque[PoseTiming] = deque(maxlen=TIMINGS_KEPT)
        self._periodic_thread = threading.Thread(target=self._periodic, daemon=True,
                                                 name=f"ros2-out-{robot_id}-periodic")

    @property
    def camera_frame(self) -> str:
        """The configured frame, else the ROS images' own, else <robot>/camera."""
        return self.cfg.camera_frame or getattr(self.source, "camera_frame_id", "") or \
            f"{self.robot_id}/camera"

    # -- lifecycle ------------------------------------------------------------------------

    def start(self) -> RobotRosOut:
        self.graph.start()
        self._periodic_thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        self._periodic_thread.join(max(self.cfg.path_every_s, self.cfg.diagnostics_every_s)
                                   + 1.0)
        with self._lock:
            for sub in self._subs:
                try:
                    sub.undeclare()
                except zenoh.ZError:
                    pass
            self._subs = []
            self._pubs = {}
        self.graph.close()
        self.report.ros2_poses = self.tracked_frames
        self.report.ros2_unpublished = self.unpublished
        self.report.ros2_timings = [
            (t.frame_index, t.taken_ns, t.sent_ns, t.feedback_ns, t.published_ns)
            for t in self.timings]

    def declare(self, node: RosNode) -> None:
        """The node is up: this robot's publishers, and subscribers to its own TF."""
        pubs = {"pose": node.publisher(self.topics["pose"], cdr.POSE_STAMPED, POSE_DEPTH),
                "tf": node.publisher("/tf", cdr.TF_MESSAGE, TF_DEPTH),
                "tf_static": node.publisher("/tf_static", cdr.TF_MESSAGE, 1,
                                            transient_local=True),
                "path": node.publisher(self.topics["path"], cdr.PATH, PATH_DEPTH),
                "diagnostics": node.publisher("/diagnostics", cdr.DIAGNOSTIC_ARRAY,
                                              DIAGNOSTICS_DEPTH)}
        ours = {pub.gid for pub in pubs.values()}
        tf_type = dds_type_name(cdr.TF_MESSAGE)
        session = node.session
        subs = [session.declare_subscriber(
                    topic_key(node.domain_id, "/tf", tf_type),
                    lambda sample: self._on_tf(sample, False, ours)),
                # Static transforms were published before we came: rmw_zenoh's publishers
                # cache them for late subscribers that look for late publishers.
                zenoh.ext.declare_advanced_subscriber(
                    session, topic_key(node.domain_id, "/tf_static", tf_type),
                    lambda sample: self._on_tf(sample, True, ours),
                    history=zenoh.ext.HistoryConfig(detect_late_publishers=True))]
        with self._lock:
            self._pubs, self._subs = pubs, subs
            placed = self._placed
        if placed is not None:
            self._publish_placed(placed)

    def _publish(self, name: str, data: bytes) -> None:
        pub = self._pubs.get(name)
        if pub is None:
            self.unpublished += 1
            return
        try:
            if not pub.publish(data):  # closed under us (shutdown)
                self.unpublished += 1
        except zenoh.ZError as exc:  # the session closed under us (shutdown)
            self.unpublished += 1
            log.debug("robot %s: ROS 2 out: %s not published: %s", self.robot_id, name, exc)

    # -- the robot's own TF ------------------------------------------------------------------

    def _on_tf(self, sample: zenoh.Sample, static: bool, ours: set[bytes]) -> None:
        where = f"{'/tf_static' if static else '/tf'} ({sample.key_expr})"
        try:
            attachment = sample.attachment
            if attachment is not None and parse_attachment(attachment.to_bytes()).gid in ours:
                return  # what this node published
            transforms = cdr.read_tf_message(sample.payload.to_bytes(), where)
        except ValueError as exc:
            self.tf_rejected += 1
            if self.tf_rejected == 1:
                log.warning("robot %s: ROS 2 out: a TF message rejected (said once): %s",
                            self.robot_id, exc)
            return
        self.tf.add(transforms, static)

    def _placed_in_tree(self, stamp: int, T_map_camera: np.ndarray
                        ) -> tuple[str, np.ndarray] | None:
        """(frame, T_map_frame) for /tf: the camera itself, or where the robot's own TF
        gives the camera a parent, the top of its tree; None (counted, said once till it
        mends) when that tree cannot place this frame."""
        camera = self.camera_frame
        try:
            if self.tf.parent(camera) is None:
                placed = camera, T_map_camera
            else:
                root = self.tf.root(camera)
                placed = root, T_map_camera @ invert(self.tf.lookup(root, camera, stamp))
        except TfError as exc:
            self.tf_skipped += 1
            problem = str(exc)
            if self._tf_problem is None:
                log.warning("robot %s: ROS 2 out: no /tf for this frame (the pose goes on): "
                            "%s", self.robot_id, problem)
            self._tf_problem = problem
            return None
        if self._tf_problem is not None:
            log.info("robot %s: ROS 2 out: /tf placed again (%s -> %s)", self.robot_id,
                     self.map_frame, placed[0])
            self._tf_problem = None
        return placed

    # -- what the robot hears ------------------------------------------------------------

    def taken(self, frame_index: int) -> None:
        """The robot took frame ``frame_index`` from its source (for the timings)."""
        with self._lock:
            self._taken[frame_index] = [time.time_ns(), None]

    def sent(self, frame_index: int) -> None:
        """Frame ``frame_index`` is coded and handed to the link (for the timings)."""
        with self._lock:
            times = self._taken.get(frame_index)
            if times is not None:
                times[1] = time.time_ns()

    def feedback(self, fb: Feedback, round_trip_s: float | None) -> None:
        """The cloud's feedback on a frame: its pose and TF out at once if it was tracked."""
        heard = time.time_ns()
        with self._lock:
            taken, sent = self._taken.pop(fb.frame_index, None) or (None, None)
            for old in [i for i in self._taken if i < fb.frame_index]:
                del self._taken[old]  # frames the link lost
            if round_trip_s is not None:
                self._round_trips.append(1000.0 * round_trip_s)
            if not fb.tracked:
                self.lost_frames += 1
                self.state = "lost"
                return
            self.state = "relocalised" if self.state == "lost" else "tracking"
            self.tracked_frames += 1
            stamp = cdr.stamp_ns(fb.timestamp)
            T = np.asarray(fb.T_world_camera, np.float64)
            self._stamps.append(stamp)
            self._poses.append(T)
        self._publish("pose", cdr.pose_stamped(stamp, self.map_frame, T))
        placed = self._placed_in_tree(stamp, T)
        if placed is not None:
            self._publish("tf", cdr.tf_message([(stamp, self.map_frame, *placed)]))
        with self._lock:
            self.timings.append(PoseTiming(fb.frame_index, taken, sent, heard, time.time_ns()))

    def placed(self, placed: Placed) -> None:
        """The cloud placed this robot's map in its group's frame (or moved it)."""
        with self._lock:
            self._placed = placed
        self._publish_placed(placed)

    def _publish_placed(self, placed: Placed) -> None:
        self._publish("tf_static", cdr.tf_message(
            [(time.time_ns(), self.fleet_frame, self.map_frame, placed.T_global_map)]))

    # -- at a low rate ---------------------------------------------------------------------

    def _periodic(self) -> None:
        cfg = self.cfg
        next_path = next_status = time.monotonic()
        while not self._stop.wait(max(0.0, min(next_path, next_status) - time.monotonic())):
            now = time.monotonic()
            if not self.graph.connected.is_set():  # the newest path and status once it is
                next_path = next_status = now + min(cfg.path_every_s, cfg.diagnostics_every_s)
                continue
            if now >= next_path:
                self.publish_path()
                next_path = now + cfg.path_every_s
            if now >= next_status:
                self.publish_status()
                next_status = now + cfg.diagnostics_every_s

    def publish_path(self) -> None:
        with self._lock:
            if self.tracked_frames == self._path_sent:
                return
            stamps, poses = list(self._stamps), np.array(self._poses).reshape(-1, 4, 4)
            self._path_sent = self.tracked_frames
        if stamps:
            self._publish("path", cdr.path(stamps[-1], self.map_frame, stamps, poses))

    def _tf_child(self) -> str:
        """The frame our /tf places under <robot>/map ('' while it cannot)."""
        try:
            return self.tf.root(self.camera_frame)
        except TfError:
            return ""

    def publish_status(self) -> None:
        with self._lock:
            state, placed = self.state, self._placed
            trips = list(self._round_trips)
        r = self.report
        skipped = r.frames_skipped + (self.live.skipped if self.live is not None else 0)
        level = {"tracking": cdr.OK, "relocalised": cdr.OK}.get(state, cdr.WARN)
        message = {"waiting": "waiting for the cloud's first pose",
                   "tracking": "tracking", "lost": "lost: relocalising",
                   "relocalised": "relocalised after being lost"}[state]
        values = [("state", state), ("frames_tracked", str(self.tracked_frames)),
                  ("frames_lost", str(self.lost_frames)), ("keyframes", str(r.keyframes)),
                  ("round_trip_ms_last", f"{trips[-1]:.1f}" if trips else ""),
                  ("round_trip_ms_median", f"{float(np.median(trips)):.1f}" if trips else ""),
                  ("frames_skipped", str(skipped)),
                  ("fleet_group", placed.group if placed is not None else ""),
                  ("tf_child", self._tf_child()), ("tf_problem", self._tf_problem or ""),
                  ("unpublished", str(self.unpublished))]
        self._publish("diagnostics", cdr.diagnostic_array(
            time.time_ns(), [(level, f"fleetslam {self.robot_id}: tracking", message,
                              self.robot_id, values)]))

"""A run's results as ROS 2 messages (``RosMessages``: serialised by rosbags' typestore, CDR),
and those messages in an MCAP file that Foxglove, ``ros2 bag play`` and the ``mcap`` tools
open (``McapOut``: written by the mcap library with each schema's ``ros2msg`` definition,
ROS 2 Humble's), or published live (visualisation/topic_view.py, with the ROS 2 graph's own
definitions). Takes plain arrays (poses N x 4 x 4, times in ns, points); what a run's
messages are is decided above (run_mcap.py)."""

from __future__ import annotations

from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np
from mcap.writer import Writer
from rosbags.typesys import Stores, get_typestore, get_types_from_msg

from fleetslam.transforms import tum_from_T

# octomap_msgs is not in rosbags' stores: its public definition (octomap_msgs/msg/Octomap).
OCTOMAP_TYPE = "octomap_msgs/msg/Octomap"
OCTOMAP_MSG = """std_msgs/Header header
bool binary
string id
float64 resolution
int8[] data
"""

# x, y, z float32 and the colour packed as rviz and Foxglove read it: 0x00RRGGBB in the
# four bytes of a float32 field named rgb (little endian).
_POINT = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<u4")])

# rosbag2's record of the QoS a topic was offered with (the ros2 profile asks for it on every
# channel), as ROS 2 Humble writes it (integers): reliable, keep last; latched topics are
# transient local with depth 1, so `ros2 bag play` offers what rviz2's /tf_static and map
# subscribers (transient local) match, and a late subscriber still gets the one message.
_QOS = """- history: 1
  depth: {depth}
  reliability: 1
  durability: {durability}
  deadline:
    sec: 0
    nsec: 0
  lifespan:
    sec: 0
    nsec: 0
  liveliness: 1
  liveliness_lease_duration:
    sec: 0
    nsec: 0
  avoid_ros_namespace_conventions: false
"""
_LATCHED_QOS = _QOS.format(depth=1, durability=1)  # RMW_QOS_POLICY_DURABILITY_TRANSIENT_LOCAL
_STREAM_QOS = _QOS.format(depth=100, durability=2)  # RMW_QOS_POLICY_DURABILITY_VOLATILE


def _typestore(store_name: str = "ROS2_HUMBLE") -> Any:
    store = get_typestore(getattr(Stores, store_name))
    if OCTOMAP_TYPE not in store.types:
        store.register(get_types_from_msg(OCTOMAP_MSG, OCTOMAP_TYPE))
    return store


def seconds_to_ns(times: np.ndarray) -> np.ndarray:
    """Seconds (TUM stamps) to integer nanoseconds, rounded to the nearest."""
    return np.round(np.asarray(times, np.float64) * 1e9).astype(np.int64)


class RosMessages:
    """Messages collected in the order they are made: ``messages`` (log time, order, topic,
    CDR), ``topics`` (topic: (type, latched)); ``store``: rosbags' typestore of the ROS 2
    distribution whose definitions they follow."""

    def __init__(self, store: str = "ROS2_HUMBLE") -> None:
        self._ts = _typestore(store)
        self._t = self._ts.types
        self.messages: list[tuple[int, int, str, bytes]] = []
        self.topics: dict[str, tuple[str, bool]] = {}

    def type_hash(self, typename: str) -> str:
        """REP-2016's hash of a type as this distribution defines it."""
        return str(self._ts.hash_rihs01(typename))

    def definition(self, typename: str) -> str:
        """The type's ``ros2msg`` definition, with those it uses (an MCAP schema's)."""
        return str(self._ts.generate_msgdef(typename, ros_version=2)[0])

    # Message pieces -----------------------------------------------------------------
    def _header(self, stamp_ns: int, frame_id: str) -> Any:
        stamp = self._t["builtin_interfaces/msg/Time"](sec=int(stamp_ns // 1_000_000_000),
                                                       nanosec=int(stamp_ns % 1_000_000_000))
        return self._t["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)

    def _poses(self, poses: np.ndarray) -> list[tuple[Any, Any]]:
        """([x, y, z], Quaternion) per pose: the translation's values for a Point or a
        Vector3, whichever the message has."""
        quaternion = self._t["geometry_msgs/msg/Quaternion"]
        return [(v[:3], quaternion(x=v[3], y=v[4], z=v[5], w=v[6]))
                for v in tum_from_T(poses).tolist()]

    def _add(self, topic: str, typename: str, log_ns: int, message: Any,
             latched: bool = False) -> None:
        known = self.topics.setdefault(topic, (typename, latched))
        if known[0] != typename:
            raise ValueError(f"topic {topic} has type {known[0]}, not {typename}")
        data = bytes(self._ts.serialize_cdr(message, typename))
        self.messages.append((int(log_ns), len(self.messages), topic, data))

    # Messages -------------------------------------------------------------------------
    def path(self, topic: str, frame_id: str, stamp_ns: int, times_ns: np.ndarray,
             poses: np.ndarray) -> None:
        """A nav_msgs/Path: every pose at its time, in ``frame_id``."""
        point, pose = self._t["geometry_msgs/msg/Point"], self._t["geometry_msgs/msg/Pose"]
        stamped = self._t["geometry_msgs/msg/PoseStamped"]
        steps = [stamped(header=self._header(t, frame_id),
                         pose=pose(position=point(x=p[0], y=p[1], z=p[2]), orientation=q))
                 for t, (p, q) in zip(times_ns.tolist(), self._poses(poses))]
        self._add(topic, "nav_msgs/msg/Path", stamp_ns,
                  self._t["nav_msgs/msg/Path"](header=self._header(stamp_ns, frame_id),
                                               poses=steps), latched=True)

    def _transforms(self, stamps_ns: list[int], parents: list[str], children: list[str],
                    poses: np.ndarray) -> list[Any]:
        vector = self._t["geometry_msgs/msg/Vector3"]
        transform = self._t["geometry_msgs/msg/Transform"]
        stamped = self._t["geometry_msgs/msg/TransformStamped"]
        return [stamped(header=self._header(t, parent), child_frame_id=child,
                        transform=transform(translation=vector(x=p[0], y=p[1], z=p[2]),
                                            rotation=q))
                for t, parent, child, (p, q) in zip(stamps_ns, parents, children,
                                                    self._poses(poses))]

    def transforms(self, topic: str, parent: str, child: str, times_ns: np.ndarray,
                   poses: np.ndarray) -> None:
        """One tf2_msgs/TFMessage per pose, at its time: ``parent`` -> ``child``."""
        n = len(times_ns)
        tf = self._t["tf2_msgs/msg/TFMessage"]
        for t, item in zip(times_ns.tolist(), self._transforms(
                times_ns.tolist(), [parent] * n, [child] * n, poses)):
            self._add(topic, "tf2_msgs/msg/TFMessage", t, tf(transforms=[item]))

    def static_transforms(self, topic: str, stamp_ns: int,
                          links: list[tuple[str, str, np.ndarray]]) -> None:
        """One latched TFMessage holding every (parent, child, T_parent_child)."""
        if not links:
            return
        items = self._transforms([stamp_ns] * len(links), [p for p, _, _ in links],
                                 [c for _, c, _ in links], np.array([T for _, _, T in links]))
        self._add(topic, "tf2_msgs/msg/TFMessage", stamp_ns,
                  self._t["tf2_msgs/msg/TFMessage"](transforms=items), latched=True)

    def cloud(self, topic: str, frame_id: str, stamp_ns: int, points: np.ndarray,
              colors: np.ndarray) -> None:
        """A sensor_msgs/PointCloud2 of x, y, z (float32) and rgb (packed), one row."""
        data = np.empty(len(points), _POINT)
        data["x"], data["y"], data["z"] = np.asarray(points, np.float32).T
        rgb = np.asarray(colors, np.uint32)
        data["rgb"] = (rgb[:, 0] << 16) | (rgb[:, 1] << 8) | rgb[:, 2]
        field = self._t["sensor_msgs/msg/PointField"]
        fields = [field(name=name, offset=_POINT.fields[name][1], datatype=field.FLOAT32,
                        count=1)
                  for name in _POINT.names]
        message = self._t["sensor_msgs/msg/PointCloud2"](
            header=self._header(stamp_ns, frame_id), height=1, width=len(data), fields=fields,
            is_bigendian=False, point_step=_POINT.itemsize,
            row_step=_POINT.itemsize * len(data), data=data.view(np.uint8),
            is_dense=bool(np.isfinite(points).all()))
        self._add(topic, "sensor_msgs/msg/PointCloud2", stamp_ns, message, latched=True)

    def octomap(self, topic: str, frame_id: str, stamp_ns: int, resolution: float,
                tree_id: str, data: bytes) -> None:
        """An octomap_msgs/Octomap holding a binary tree's data (``writeBinaryData``'s)."""
        message = self._t[OCTOMAP_TYPE](
            header=self._header(stamp_ns, frame_id), binary=True, id=tree_id,
            resolution=float(resolution), data=np.frombuffer(data, np.int8))
        self._add(topic, OCTOMAP_TYPE, stamp_ns, message, latched=True)

    def lines(self, topic: str, frame_id: str, stamp_ns: int, namespace: str,
              groups: list[tuple[np.ndarray, tuple[float, float, float, float]]],
              width_m: float) -> None:
        """A visualization_msgs/MarkerArray: one LINE_LIST marker per (segments K x 2 x 3,
        rgba) group, numbered in order; an empty group still gets its (empty) marker, so a
        player replaces what an earlier message drew."""
        t = self._t
        marker = t["visualization_msgs/msg/Marker"]
        markers = []
        for number, (segments, rgba) in enumerate(groups):
            ends = [t["geometry_msgs/msg/Point"](x=p[0], y=p[1], z=p[2])
                    for p in np.asarray(segments, np.float64).reshape(-1, 3).tolist()]
            markers.append(marker(
                header=self._header(stamp_ns, frame_id), ns=namespace, id=number,
                type=marker.LINE_LIST, action=marker.ADD,
                pose=t["geometry_msgs/msg/Pose"](
                    position=t["geometry_msgs/msg/Point"](x=0.0, y=0.0, z=0.0),
                    orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0,
                                                                   w=1.0)),
                scale=t["geometry_msgs/msg/Vector3"](x=width_m, y=0.0, z=0.0),
                color=t["std_msgs/msg/ColorRGBA"](r=rgba[0], g=rgba[1], b=rgba[2],
                                                   a=rgba[3]),
                lifetime=t["builtin_interfaces/msg/Duration"](sec=0, nanosec=0),
                frame_locked=False, points=ends, colors=[], texture_resource="",
                texture=t["sensor_msgs/msg/CompressedImage"](
                    header=self._header(stamp_ns, ""), format="", data=np.zeros(0, np.uint8)),
                uv_coordinates=[], text="", mesh_resource="",
                mesh_file=t["visualization_msgs/msg/MeshFile"](filename="",
                                                               data=np.zeros(0, np.uint8)),
                mesh_use_embedded_materials=False))
        self._add(topic, "visualization_msgs/msg/MarkerArray", stamp_ns,
                  t["visualization_msgs/msg/MarkerArray"](markers=markers), latched=True)


    def grid(self, topic: str, frame_id: str, stamp_ns: int, cells: np.ndarray,
             resolution: float, T_frame_origin: np.ndarray) -> None:
        """A nav_msgs/OccupancyGrid: ``cells`` (H x W int8, -1 unknown, 0 free, 100
        occupied; row 0 the one at the origin), the lower-left cell's corner at
        ``T_frame_origin`` in ``frame_id``."""
        t = self._t
        height, width = cells.shape
        (position, orientation), = self._poses(np.asarray(T_frame_origin)[None])
        info = t["nav_msgs/msg/MapMetaData"](
            map_load_time=self._header(stamp_ns, "").stamp, resolution=float(resolution),
            width=width, height=height,
            origin=t["geometry_msgs/msg/Pose"](
                position=t["geometry_msgs/msg/Point"](x=position[0], y=position[1],
                                                      z=position[2]),
                orientation=orientation))
        self._add(topic, "nav_msgs/msg/OccupancyGrid", stamp_ns,
                  t["nav_msgs/msg/OccupancyGrid"](
                      header=self._header(stamp_ns, frame_id), info=info,
                      data=np.ascontiguousarray(cells, np.int8).ravel()), latched=True)


class McapOut(RosMessages):
    """Collects messages, then writes them in log-time order on ``close`` (a reader that
    streams the file sees time move forward); the file appears whole or not at all."""

    def __init__(self, path: Path) -> None:
        super().__init__()
        self.file = Path(path)

    def __enter__(self) -> McapOut:
        return self

    def __exit__(self, kind: type[BaseException] | None, value: BaseException | None,
                 tb: TracebackType | None) -> None:
        if kind is None:
            self.close()

    def close(self) -> None:
        self.file.parent.mkdir(parents=True, exist_ok=True)
        partial = self.file.with_name(self.file.name + ".part")
        with open(partial, "wb") as f:
            writer = Writer(f)
            writer.start(profile="ros2", library="fleetslam")
            channels = {}
            for topic, (typename, latched) in self.topics.items():
                schema = writer.register_schema(
                    name=typename, encoding="ros2msg",
                    data=self.definition(typename).encode())
                channels[topic] = writer.register_channel(
                    topic=topic, message_encoding="cdr", schema_id=schema,
                    metadata={"offered_qos_profiles": _LATCHED_QOS if latched
                              else _STREAM_QOS})
            for log_ns, _, topic, data in sorted(self.messages):
                writer.add_message(channels[topic], log_time=log_ns, data=data,
                                   publish_time=log_ns)
            writer.finish()
        partial.replace(self.file)

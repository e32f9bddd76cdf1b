"""ROS 1 and ROS 2 bags as a recorded source: a ROS 1 ``.bag``, a ROS 2 bag folder
(``metadata.yaml``, sqlite3 or MCAP storage) or a lone ``.mcap`` / ``.db3`` file, read with
rosbags (the robot's ``ros`` extra, imported only when a bag is opened).

Nothing of the bag is held whole: one streaming pass reads each colour and depth message's
header stamp and where to find it again (topic, bag time, its rank among that topic's
messages of the same bag time). Colour and depth are paired one-to-one by nearest header
stamp within ``SourceConfig.pair_tolerance_s``; the rest is counted as unpaired. A frame is
read again by seeking to its messages' bag time; sequential play continues one message
stream, and a jump back (an old keyframe's images, read again) uses a second stream so the
play stream keeps its place.
"""

from __future__ import annotations

import logging
import threading
from collections import OrderedDict
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from fleetslam.camera import Camera
from fleetslam.config import SourceConfig
from fleetslam.datasets.ranges import play_order, repeated_text
from fleetslam.datasets.ros2_discovery import preferred_images
from fleetslam.datasets.ros_messages import (
    CAMERA_INFO_TYPE, COLOUR_ENCODINGS, DEPTH_ENCODINGS, IMAGE_TYPES, camera_from_info,
    colour_image, depth_image, depth_image_scale, image_format, image_role, stamp_seconds)
from fleetslam.datasets.source import Frame
from fleetslam.datasets.tum import associate

log = logging.getLogger(__name__)

ROS_EXTRA = "pip install 'fleetslam[ros]'"
# Files rosbags opens as a bag by themselves (a ROS 2 bag folder has metadata.yaml).
BAG_SUFFIXES = (".bag", ".mcap", ".db3")
# A frame further ahead than this (bag time) is reached by seeking, not by reading through
# the messages in between (~1 MB each for raw images).
SEEK_AHEAD_NS = 500_000_000
# Messages read on the way to a frame and kept for the next frames (raw, one image each).
READ_AHEAD_MESSAGES = 8

Key = tuple[str, int, int]  # topic, bag time ns, rank among its messages of that bag time


class BagError(ValueError):
    """A bag fleetslam cannot play; the text names the bag (and topic)."""


def is_bag(path: Path) -> bool:
    """A ROS 1 bag file, a ROS 2 bag folder, or a lone ROS 2 storage file (a missing file
    named like one too, so that it is reported as a missing bag)."""
    if path.is_dir():
        return (path / "metadata.yaml").is_file()
    return path.suffix in BAG_SUFFIXES


def _open_reader(path: Path) -> Any:
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
    except ModuleNotFoundError as exc:
        raise BagError(f"{path}: reading a ROS bag needs the ros extra: {ROS_EXTRA} "
                       f"(no module named {exc.name!r})") from None
    # Used only where the bag carries no message definitions (older ROS 2 sqlite3 bags).
    store = Stores.ROS1_NOETIC if path.suffix == ".bag" else Stores.ROS2_HUMBLE
    reader = AnyReader([path], default_typestore=get_typestore(store))
    try:
        reader.open()
    except Exception as exc:  # rosbags raises its own error types, and struct/OS errors
        raise BagError(f"{path}: not a readable ROS bag (damaged or truncated?): "
                       f"{exc}") from None
    return reader


@dataclass(frozen=True)
class _Topic:
    name: str
    msgtype: str
    count: int
    first: Any  # the first message, decoded (encoding, CameraInfo)

    def describe(self) -> str:
        what = f" {image_format(self.first)}" if self.msgtype in IMAGE_TYPES else ""
        return f"{self.name} ({self.msgtype}{what}, {self.count} messages)"


def _namespace_siblings(topic: str, name: str) -> Iterator[str]:
    """``name`` in the topic's namespace, then in each enclosing one (image_transport puts
    a compressed image one level below its base topic)."""
    parts = topic.strip("/").split("/")[:-1]
    while parts:
        yield "/" + "/".join(parts + [name])
        parts.pop()


class _MessageStream:
    """Raw messages of some topics in bag time order, from a seek point on; finds the
    messages of a frame by key, keeping a few read on the way for the next frames."""

    def __init__(self, reader: Any, connections: list[Any], needed: set[Key]) -> None:
        self._reader = reader
        self._connections = connections
        self._needed = needed
        self._messages: Iterator[tuple[Any, int, bytes]] | None = None
        self._pos = 0  # bag time of the last message read
        self._last: dict[str, tuple[int, int]] = {}  # topic -> (bag time, rank) last read
        self._kept: OrderedDict[Key, bytes] = OrderedDict()

    def fetch(self, keys: Sequence[Key]) -> list[bytes] | None:
        found = {k: self._kept.pop(k) for k in keys if k in self._kept}
        missing = {k for k in keys if k not in found}
        if missing:
            start = min(k[1] for k in missing)
            if self._messages is None or start < self._pos or start - self._pos > SEEK_AHEAD_NS:
                self._seek(start)
            # Not found: passed already (read at the same bag time as the last frame); once
            # more from a fresh seek.
            if not self._read_until(missing, found):
                self._seek(start)
                if not self._read_until(missing, found):
                    return None
        return [found[k] for k in keys]

    def _seek(self, start: int) -> None:
        self._messages = self._reader.messages(self._connections, start=start)
        self._pos = start
        self._last = {}

    def _read_until(self, missing: set[Key], found: dict[Key, bytes]) -> bool:
        assert self._messages is not None
        end = max(k[1] for k in missing)
        for conn, ns, raw in self._messages:
            last_ns, last_rank = self._last.get(conn.topic, (-1, -1))
            key = (conn.topic, ns, last_rank + 1 if last_ns == ns else 0)
            self._last[conn.topic] = key[1:]
            self._pos = ns
            if key in missing:
                found[key] = raw
                missing.discard(key)
                if not missing:
                    return True
            elif key in self._needed:
                self._kept[key] = raw
                if len(self._kept) > READ_AHEAD_MESSAGES:
                    self._kept.popitem(last=False)
            if ns > end:
                return False
        self._messages = None
        return False


class BagSequence:
    """The paired colour and depth frames of one bag, optionally some frame ranges of it
    (as ``RgbdSequence``: ranges played in turn, backwards ones re-timed)."""

    def __init__(self, path: str | Path, camera: Camera | None = None,
                 segments: list[tuple[int, int]] | None = None,
                 config: SourceConfig | None = None) -> None:
        self.folder = Path(path)
        self.camera_frame_id = ""  # the colour images' header frame_id, once one is read
        self.topic_choice = ""  # the image topics passed over and why ("" if none were)
        config = config or SourceConfig()
        if not self.folder.exists():
            raise BagError(f"{self.folder}: no such bag")
        self._reader = _open_reader(self.folder)
        try:
            self._topics = self._read_topics()
            self.rgb_topic, self.depth_topic = self._choose_image_topics(config)
            rgb, depth = self._index()
        except BagError:
            raise
        except Exception as exc:  # a damaged message or chunk met while reading through
            raise BagError(f"{self.folder}: not a readable ROS bag (damaged or truncated?): "
                           f"{type(exc).__name__}: {exc}") from None
        depth_first = self._topics[self.depth_topic].first
        self._depth_scale = depth_image_scale(depth_first, self._where(self.depth_topic))
        self.camera, camera_source = self._camera(camera, config)

        rgb_ns, rgb_rank, rgb_t = rgb
        depth_ns, depth_rank, depth_t = depth
        pairs = self._pairs(rgb_t, depth_t, config.pair_tolerance_s)
        self.pairs = len(pairs)
        self.unpaired_rgb = len(rgb_t) - len(pairs)
        self.unpaired_depth = len(depth_t) - len(pairs)
        ci = np.array([i for i, _ in pairs])
        di = np.array([j for _, j in pairs])
        played = play_order(rgb_t[ci], segments, str(self.folder))
        ci, di = ci[played.order], di[played.order]
        self.first = int(played.order[0])
        self.recorded_timestamps = played.recorded_timestamps
        self.timestamps = played.timestamps
        self.retimed, self.repeated = played.retimed, played.repeated
        self._rgb_keys: list[Key] = [(self.rgb_topic, int(rgb_ns[i]), int(rgb_rank[i]))
                                     for i in ci]
        self._depth_keys: list[Key] = [(self.depth_topic, int(depth_ns[j]),
                                        int(depth_rank[j])) for j in di]
        self.camera_source = "; ".join(filter(None, [camera_source, (
            f"{self.pairs} colour/depth pairs, unpaired {self.unpaired_rgb} colour and "
            f"{self.unpaired_depth} depth"), repeated_text(self.repeated)]))
        log.log(logging.WARNING if self.repeated else logging.INFO,
                "%s: colour %s and depth %s%s, camera %s", self.folder, self.rgb_topic,
                self.depth_topic, f" ({self.topic_choice})" if self.topic_choice else "",
                self.camera_source)
        connections = [c for c in self._reader.connections
                       if c.topic in (self.rgb_topic, self.depth_topic)]
        needed = set(self._rgb_keys) | set(self._depth_keys)
        # Play goes forward through the bag; reading an older frame again must not lose
        # its place, so it has a stream of its own.
        self._play = _MessageStream(self._reader, connections, needed)
        self._revisit = _MessageStream(self._reader, connections, needed)
        self._played_to = -1
        self._lock = threading.Lock()  # one reader: the robot's uploader reads too

    # -- opening -----------------------------------------------------------------------

    def _pairs(self, rgb_t: np.ndarray, depth_t: np.ndarray, tolerance_s: float
               ) -> list[tuple[int, int]]:
        """Colour and depth frames paired by stamp; BagError if none are."""
        pairs = associate(rgb_t, depth_t, tolerance_s)
        if not pairs:
            raise BagError(
                f"{self.folder}: no colour/depth pair closer than {tolerance_s * 1000:.0f} ms "
                f"({self.rgb_topic} stamps {rgb_t[0]:.3f}..{rgb_t[-1]:.3f}, "
                f"{self.depth_topic} {depth_t[0]:.3f}..{depth_t[-1]:.3f})")
        return pairs

    def _where(self, topic: str) -> str:
        return f"{self.folder} topic {topic}"

    def _read_topics(self) -> dict[str, _Topic]:
        """Every image and CameraInfo topic with its first message (one message each)."""
        topics = {}
        for name, info in self._reader.topics.items():
            if info.msgtype not in IMAGE_TYPES + (CAMERA_INFO_TYPE,) or not info.msgcount:
                continue
            conns = [c for c in self._reader.connections if c.topic == name]
            conn, _, raw = next(iter(self._reader.messages(conns)))
            topics[name] = _Topic(name, info.msgtype, info.msgcount,
                                  self._reader.deserialize(raw, conn.msgtype))
        return topics

    def _image_topics(self) -> str:
        images = [t.describe() for t in self._topics.values() if t.msgtype in IMAGE_TYPES]
        return "image topics: " + ("; ".join(images) if images else "none")

    def _choose_image_topics(self, config: SourceConfig) -> tuple[str, str]:
        chosen, passed = [], []
        for role, given, flag, encodings in (
                ("colour", config.rgb_topic, "--rgb-topic", COLOUR_ENCODINGS),
                ("depth", config.depth_topic, "--depth-topic", DEPTH_ENCODINGS)):
            if given:
                topic = self._topics.get(given)
                if topic is None or topic.msgtype not in IMAGE_TYPES:
                    raise BagError(f"{self.folder}: {flag} {given} is not an image topic of "
                                   f"the bag ({self._image_topics()})")
                chosen.append(given)
                continue
            name, passed_over = self._auto_topic(role, flag, encodings)
            chosen.append(name)
            passed += passed_over
        self.topic_choice = f"chosen over {', '.join(passed)}" if passed else ""
        rgb, depth = chosen
        for topic, role, encodings in ((rgb, "colour", COLOUR_ENCODINGS),
                                       (depth, "depth", DEPTH_ENCODINGS)):
            found = image_role(self._topics[topic].first)
            if found != role:
                what = f"is {found}" if found else "has an unsupported encoding"
                raise BagError(f"{self._where(topic)}: {what} "
                               f"({image_format(self._topics[topic].first)!r}), not {role} "
                               f"(use one of {', '.join(encodings)}"
                               f"{'' if role == 'depth' else ', or a JPEG/PNG CompressedImage'})")
        return rgb, depth

    def _auto_topic(self, role: str, flag: str, encodings: tuple[str, ...]
                    ) -> tuple[str, list[str]]:
        """The one image topic of ``role`` a user means (``preferred_images``: the raw topic
        over its image_transport copies, depth aligned to colour over unaligned) and the
        topics passed over; BagError naming the image topics when that is not one."""
        candidates, passed = preferred_images(
            [t.name for t in self._topics.values()
             if t.msgtype in IMAGE_TYPES and image_role(t.first) == role], role)
        if len(candidates) == 1:
            return candidates[0], passed
        unread = [t.describe() for t in self._topics.values()
                  if t.msgtype in IMAGE_TYPES and image_role(t.first) is None]
        why = (f"{len(candidates)} {role} image topics, choose one with {flag}"
               if candidates else f"no {role} image topic"
               + (f" fleetslam reads ({role} encodings: {', '.join(encodings)}; "
                  f"unsupported: {'; '.join(unread)})" if unread else ""))
        raise BagError(f"{self.folder}: {why} ({self._image_topics()})")

    def _index(self) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray], ...]:
        """(bag time, rank, header stamp) of every colour and every depth message, in one
        pass over their messages; every message's encoding must be its topic's first."""
        conns = [c for c in self._reader.connections
                 if c.topic in (self.rgb_topic, self.depth_topic)]
        rows: dict[str, list[tuple[int, int, float]]] = {self.rgb_topic: [],
                                                         self.depth_topic: []}
        for conn, ns, raw in self._reader.messages(conns):
            msg = self._reader.deserialize(raw, conn.msgtype)
            topic = self._topics[conn.topic]
            fmt, first = image_format(msg), image_format(topic.first)
            if fmt != first:
                raise BagError(f"{self._where(conn.topic)}: encoding changes from {first!r} "
                               f"to {fmt!r} at message {len(rows[conn.topic])}; fleetslam "
                               f"needs one encoding a topic")
            topic_rows = rows[conn.topic]
            rank = topic_rows[-1][1] + 1 if topic_rows and topic_rows[-1][0] == ns else 0
            topic_rows.append((ns, rank, stamp_seconds(msg)))
        out = []
        for topic in (self.rgb_topic, self.depth_topic):
            ns, rank, stamp = zip(*rows[topic]) if rows[topic] else ((), (), ())
            out.append((np.array(ns, np.int64), np.array(rank, np.int64),
                        np.array(stamp, np.float64)))
        return tuple(out)

    def _info_topic(self, image_topic: str, given: str) -> str | None:
        infos = [t for t in self._topics.values() if t.msgtype == CAMERA_INFO_TYPE]
        if given:
            if given not in self._topics or self._topics[given].msgtype != CAMERA_INFO_TYPE:
                raise BagError(f"{self.folder}: --camera-info-topic {given} is not a "
                               f"CameraInfo topic of the bag (CameraInfo topics: "
                               f"{', '.join(t.describe() for t in infos) or 'none'})")
            return given
        for sibling in _namespace_siblings(image_topic, "camera_info"):
            if sibling in self._topics and self._topics[sibling].msgtype == CAMERA_INFO_TYPE:
                return sibling
        return infos[0].name if len(infos) == 1 else None

    def _camera(self, camera: Camera | None, config: SourceConfig) -> tuple[Camera, str]:
        """The camera and where it came from. The depth scale is the depth topic's
        (REP 118), also with a given camera: the raw depth images are made here."""
        if camera is not None:
            return replace(camera, depth_scale=self._depth_scale, invalid_depth=(0,)), "given"
        info = self._info_topic(self.rgb_topic, config.camera_info_topic)
        if info is None:
            infos = [t.describe() for t in self._topics.values()
                     if t.msgtype == CAMERA_INFO_TYPE]
            raise BagError(f"{self.folder}: no CameraInfo for {self.rgb_topic} (CameraInfo "
                           f"topics: {'; '.join(infos) or 'none'}); give --camera-info-topic "
                           f"or --camera camera.json")
        depth_info = self._info_topic(self.depth_topic, "")
        depth_info = depth_info if depth_info != info else None
        camera = camera_from_info(
            self._topics[info].first, self._where(info), self._depth_scale,
            self._topics[depth_info].first if depth_info else None,
            self._where(depth_info) if depth_info else "")
        source = f"CameraInfo {info}" + (f", depth pinhole from {depth_info}"
                                         if camera.depth_intrinsics else "")
        return camera, source

    # -- RecordedSource ----------------------------------------------------------------

    @property
    def gt_poses(self) -> np.ndarray | None:
        return None  # a bag carries no ground truth

    @property
    def has_ground_truth(self) -> bool:
        return False

    def __len__(self) -> int:
        return len(self.timestamps)

    def __getitem__(self, i: int) -> Frame:
        if not 0 <= i < len(self):
            raise IndexError(i)
        keys = (self._rgb_keys[i], self._depth_keys[i])
        with self._lock:
            stream = self._play if i >= self._played_to else self._revisit
            self._played_to = max(self._played_to, i)
            try:
                raws = stream.fetch(keys)
            except Exception as exc:  # a damaged chunk or record past the index
                raise BagError(f"{self.folder}: cannot read frame {i} (damaged or "
                               f"truncated?): {type(exc).__name__}: {exc}") from None
            if raws is None:
                raise BagError(f"{self.folder}: frame {i}'s messages at bag time "
                               f"{keys[0][1]} / {keys[1][1]} ns are not in the bag any more")
            rgb_msg, depth_msg = (self._reader.deserialize(raw, self._topics[k[0]].msgtype)
                                  for raw, k in zip(raws, keys))
        # The camera's TF frame, for what the robot publishes back (edge/ros2_out.py).
        self.camera_frame_id = str(rgb_msg.header.frame_id).lstrip("/")
        rgb = colour_image(rgb_msg, self._where(self.rgb_topic))
        raw = depth_image(depth_msg, self._where(self.depth_topic), self._depth_scale)
        if raw.shape != rgb.shape[:2]:
            raise BagError(f"{self._where(self.depth_topic)}: depth {raw.shape[1]} x "
                           f"{raw.shape[0]} and colour {rgb.shape[1]} x {rgb.shape[0]} "
                           f"({self.rgb_topic}) differ in size at frame {i}")
        cam = self.camera
        if (cam.width, cam.height) != (raw.shape[1], raw.shape[0]):
            self.camera = cam = replace(cam, width=raw.shape[1], height=raw.shape[0])
        return Frame(i, float(self.timestamps[i]), rgb, raw, cam.depth_to_metres(raw))

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self[i]

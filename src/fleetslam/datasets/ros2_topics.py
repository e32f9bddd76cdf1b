"""Live ROS 2 camera topics of a robot whose ROS 2 runs rmw_zenoh, read straight off Zenoh
(no ROS 2 install): a ``LiveSource``.

The source is a Zenoh client of the robot's ROS 2 router (``[source] ros_endpoint``, or the
spec ``ros2:ENDPOINT``). It finds the camera's topics from rmw_zenoh's liveliness tokens
unless configured, subscribes to their data keys with any type hash (Humble's placeholder,
Iron/Jazzy/Rolling's RIHS01 hashes alike: ``datasets.rmw_zenoh``), reads the camera model
from the first CameraInfo, and pairs colour and depth by header stamp as they arrive
(``datasets.stamp_pairing``); each pair goes into a ``NewestFrame`` slot as received.
Subscriber callbacks only read each message's stamp (a few microseconds); rosbags decodes a
pair, and it becomes a Frame, when the robot takes it: a pair the robot skips costs nothing
(a 32FC1 depth image alone takes 5-10 ms to convert on this machine).
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections import Counter
from collections.abc import Callable
from typing import Any

import numpy as np
import zenoh

from fleetslam.camera import Camera
from fleetslam.config import Config, SourceConfig
from fleetslam.datasets.live import NewestFrame, SlotCounts
from fleetslam.datasets.rmw_zenoh import (
    Endpoint,
    header_stamp,
    key_topic,
    key_type,
    liveliness_key,
    parse_attachment,
    parse_liveliness,
    topic_key,
)
from fleetslam.datasets.ros2_session import open_ros_session
from fleetslam.datasets.ros2_discovery import (
    CameraTopics,
    TopicChoiceError,
    choose_topics,
    describe,
    image_candidates,
    published_types,
)
from fleetslam.datasets.ros_messages import (
    CAMERA_INFO_TYPE,
    IMAGE_TYPES,
    RosMessageError,
    camera_from_info,
    colour_image,
    depth_image,
    depth_image_scale,
)
from fleetslam.datasets.source import Frame
from fleetslam.datasets.stamp_pairing import COLOUR, DEPTH, StampPairer
from fleetslam.validation.endpoints import check_endpoint

log = logging.getLogger("fleetslam.datasets.ros2")
# A skipped camera message is said the first time and then once every this many.
REJECTED_SAID_EVERY = 100

SPEC = "ros2"
# What the message types are decoded with: sensor_msgs is the same in Humble and Jazzy.
_TYPESTORE = "ROS2_JAZZY"


def is_ros2_spec(spec: str) -> bool:
    """``ros2`` or ``ros2:ENDPOINT`` (a folder named ros2 is ``./ros2``)."""
    return spec == SPEC or spec.startswith(SPEC + ":")


def resolve_domain_id(configured: int) -> int:
    """The configured ROS domain, or ROS 2's own rule: ROS_DOMAIN_ID, else 0."""
    if configured >= 0:
        return configured
    value = os.environ.get("ROS_DOMAIN_ID", "").strip()
    if not value:
        return 0
    if not value.isdigit():
        raise ValueError(f"ROS_DOMAIN_ID={value!r} is not a domain id (0-232)")
    return int(value)


def _typestore() -> Any:
    try:
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise RuntimeError("ROS 2 topics are decoded with rosbags, which this install lacks: "
                           "pip install 'fleetslam[ros]'") from None
    return get_typestore(getattr(Stores, _TYPESTORE))



# A message as received: CDR payload, ROS type, Zenoh key.
Message = tuple[bytes, str, str]
Pair = tuple[Message, Message, float]  # colour, depth, colour stamp


def _writable(array: np.ndarray) -> np.ndarray:
    # Decoded images may be views of the received bytes, which are read-only.
    return array if array.flags.writeable else array.copy()


class Ros2TopicSource(SlotCounts):
    """Colour + depth + CameraInfo topics of a ROS 2 camera, live over rmw_zenoh."""

    def __init__(self, endpoint: str, config: SourceConfig, camera: Camera | None = None
                 ) -> None:
        """``camera``: a calibration to use instead of the topics' CameraInfo."""
        self.endpoint = endpoint
        self.config = config
        self.domain_id = resolve_domain_id(config.ros_domain_id)
        self.description = f"ROS 2 topics over rmw_zenoh at {endpoint} (domain {self.domain_id})"
        self.camera: Camera = camera  # type: ignore[assignment]  # known once started
        self.camera_source = "given" if camera is not None else ""
        self.topics: CameraTopics | None = None
        self._given_camera = camera
        self._slot: NewestFrame[Pair] = NewestFrame()
        self._cond = threading.Condition()
        self._session: zenoh.Session | None = None
        self._subscribers: list[Any] = []
        self._store: Any = None
        self._alive: dict[str, Endpoint] = {}  # liveliness key -> endpoint
        self._alive_changed = time.monotonic()
        self._infos: dict[str, tuple[Any, str]] = {}  # topic -> first CameraInfo, its key
        self._depth_scale: float | None = camera.depth_scale if camera is not None else None
        self._started = False  # camera known: images are paired from now on
        self._pairer: StampPairer[Message] = StampPairer(
            config.pair_tolerance_s, config.ros_waiting_messages)
        self._sequences: dict[bytes, int] = {}  # publisher GID -> last sequence number
        self._error: BaseException | None = None
        self.received: Counter[str] = Counter()  # messages per topic
        self.lost = 0  # messages missing in a publisher's sequence numbers
        self.bad_attachments = 0  # messages whose attachment is not rmw_zenoh's
        self.camera_frame_id = ""  # the colour images' header frame_id, once one is read

    @classmethod
    def from_spec(cls, spec: str, config: Config, camera: Camera | None = None
                  ) -> Ros2TopicSource:
        """``ros2`` (the router at ``[source] ros_endpoint``) or ``ros2:ENDPOINT``."""
        if not is_ros2_spec(spec):
            raise ValueError(f"{spec!r} is not a ROS 2 topics source (ros2 or ros2:ENDPOINT)")
        endpoint = spec[len(SPEC) + 1:] if spec.startswith(SPEC + ":") \
            else config.source.ros_endpoint
        check_endpoint(endpoint, f"source {spec!r}: endpoint",
                       config.source.ros_zenoh_config or None)
        return cls(endpoint, config.source, camera)

    # ------------------------------------------------------------------ LiveSource

    def start(self, timeout: float) -> None:
        try:
            self._start(timeout)
        except BaseException:
            self.close()  # a failed start leaves no session or subscriber behind
            raise

    def _start(self, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        self._store = _typestore()
        self._session = open_ros_session(
            self.endpoint, timeout, self.config.ros_zenoh_config,
            hint="Set it with [source] ros_endpoint or the source spec ros2:ENDPOINT")
        with self._cond:
            self._alive_changed = time.monotonic()
        self._subscribers.append(self._session.liveliness().declare_subscriber(
            liveliness_key(self.domain_id), self._on_liveliness, history=True))
        self.topics = topics = self._choose_topics(deadline, timeout)
        if topics.why:
            log.info("ROS 2 topics %s and %s %s", topics.colour, topics.depth, topics.why)
        self.description = (f"ROS 2 topics {topics.colour} + {topics.depth} over rmw_zenoh at "
                            f"{self.endpoint} (domain {self.domain_id})")
        self._subscribe(topic_key(self.domain_id, topics.colour), self._on_image(COLOUR))
        self._subscribe(topic_key(self.domain_id, topics.depth), self._on_image(DEPTH))
        if self._given_camera is None:
            for info in {topics.colour_info, topics.depth_info}:
                self._subscribe(topic_key(self.domain_id, info), self._on_info(info))
        self._wait_for_camera(deadline, timeout)
        log.info("%s: camera from %s", self.description, self.camera_source)

    def take(self, timeout: float) -> Frame | None:
        """The newest frame; a pair of messages that is not one (not CDR, an image that does
        not decode or is not the camera's size) is skipped and counted (``rejected``), said
        in one line the first time and every REJECTED_SAID_EVERY after."""
        deadline = time.monotonic() + timeout
        while True:
            pair = self._slot.take(max(deadline - time.monotonic(), 0.0))
            if pair is None:
                return None
            try:
                frame = self._frame(*pair)
            except RosMessageError as exc:
                self.rejected += 1
                if self.rejected % REJECTED_SAID_EVERY == 1:
                    log.warning("%s: a camera message skipped (%d so far): %s",
                                self.description, self.rejected, exc)
                continue
            except Exception as exc:
                self._fail(exc)  # not the message's fault: the next would fail the same way
                raise
            frame.index = self._slot.taken - 1
            return frame

    @property
    def unpaired(self) -> int:
        """Images dropped without a partner within ``pair_tolerance_s``."""
        with self._cond:
            return self._pairer.unpaired

    def close(self) -> None:
        self._slot.close()
        for subscriber in self._subscribers:
            try:
                subscriber.undeclare()
            except zenoh.ZError:
                pass  # the session is already gone
        self._subscribers.clear()
        if self._session is not None:
            self._session.close()
            self._session = None

    # ------------------------------------------------------------------ start's waits

    def _seen(self) -> str:
        """What is alive and what arrived, for messages (call with the lock held)."""
        topics = published_types(self._alive.values())
        if not topics:
            alive = (f"no ROS 2 publisher is alive at {self.endpoint} in domain "
                     f"{self.domain_id} (is that the robot's ROS 2 router, and its "
                     f"ROS_DOMAIN_ID?)")
        else:
            alive = f"live topics at {self.endpoint}, domain {self.domain_id}: {describe(topics)}"
        got = ", ".join(f"{t} {n}" for t, n in sorted(self.received.items())) or "none"
        return f"{alive}; messages received: {got}"

    def _choose_topics(self, deadline: float, timeout: float) -> CameraTopics:
        config = self.config
        if config.rgb_topic and config.depth_topic:
            return choose_topics({}, config.rgb_topic, config.depth_topic,
                                 config.camera_info_topic)
        with self._cond:
            while True:
                now = time.monotonic()
                settle_left = self._alive_changed + config.ros_discovery_settle_s - now
                if settle_left <= 0:
                    topics = published_types(self._alive.values())
                    try:
                        return choose_topics(topics, config.rgb_topic, config.depth_topic,
                                             config.camera_info_topic)
                    except TopicChoiceError:
                        colours, depths = image_candidates(topics)
                        if (not config.rgb_topic and len(colours) > 1) or \
                                (not config.depth_topic and len(depths) > 1):
                            raise  # more publishers will not make it less ambiguous
                left = deadline - now
                if left <= 0:
                    raise TimeoutError(f"no colour and depth image topics to read in "
                                       f"{timeout:.1f} s: {self._seen()}")
                self._cond.wait(min(left, settle_left) if settle_left > 0 else left)

    def _missing(self) -> list[str]:
        """What the camera model still waits for (call with the lock held)."""
        if self._given_camera is not None:
            return []
        assert self.topics is not None
        missing = []
        if self.topics.colour_info not in self._infos:
            missing.append(f"a CameraInfo on {self.topics.colour_info}")
        if self._depth_scale is None:
            missing.append(f"a depth image on {self.topics.depth} (its encoding sets the "
                           f"depth scale)")
        depth_info_alive = any(e.topic == self.topics.depth_info
                               for e in self._alive.values())
        if depth_info_alive and self.topics.depth_info not in self._infos:
            missing.append(f"the CameraInfo on {self.topics.depth_info}")
        return missing

    def _wait_for_camera(self, deadline: float, timeout: float) -> None:
        with self._cond:
            while True:
                if self._error is not None:
                    raise self._error
                missing = self._missing()
                if not missing:
                    break
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError(f"no camera model from ROS 2 topics in {timeout:.1f} s: "
                                       f"waiting for {'; '.join(missing)}; {self._seen()}")
                self._cond.wait(left)
            if self._given_camera is None:
                self.camera, self.camera_source = self._camera_from_infos()
            self._started = True

    def _camera_from_infos(self) -> tuple[Camera, str]:
        assert self.topics is not None and self._depth_scale is not None
        info, where = self._infos[self.topics.colour_info]
        depth_info, depth_where = self._infos.get(self.topics.depth_info, (None, ""))
        if self.topics.depth_info == self.topics.colour_info:
            depth_info = None  # colour and depth share one camera_info: one model
        camera = camera_from_info(info, where, self._depth_scale, depth_info, depth_where)
        source = f"CameraInfo {self.topics.colour_info}"
        if depth_info is not None:
            source += f" and {self.topics.depth_info}"
        return camera, source

    # ------------------------------------------------------------------ callbacks

    def _subscribe(self, key: str, callback: Callable[[zenoh.Sample], None]) -> None:
        assert self._session is not None
        self._subscribers.append(self._session.declare_subscriber(key, callback))

    def _fail(self, exc: BaseException) -> None:
        """A camera message fleetslam cannot use ends the stream with its reason."""
        with self._cond:
            if self._error is None:
                self._error = exc
                log.error("%s: %s", self.description, exc)
            self._cond.notify_all()
        self._slot.close(exc)

    def _on_liveliness(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        endpoint = parse_liveliness(key)
        if endpoint is None:
            return
        with self._cond:
            if sample.kind == zenoh.SampleKind.DELETE:
                self._alive.pop(key, None)
            else:
                self._alive[key] = endpoint
            self._alive_changed = time.monotonic()
            self._cond.notify_all()

    def _count(self, key: str, attachment: zenoh.ZBytes | None) -> None:
        """Count a message and the publisher's sequence numbers it skipped (lock held)."""
        self.received[key_topic(key)] += 1
        if attachment is None:
            return
        try:
            info = parse_attachment(attachment.to_bytes())
        except ValueError as exc:
            if self.bad_attachments == 0:
                log.warning("%s: %s (sequence gaps are not counted)", key, exc)
            self.bad_attachments += 1
            return
        last = self._sequences.get(info.gid)
        if last is not None and info.sequence_number > last + 1:
            self.lost += info.sequence_number - last - 1
        self._sequences[info.gid] = info.sequence_number

    def _decode(self, payload: bytes, ros_type: str, where: str) -> Any:
        try:
            return self._store.deserialize_cdr(payload, ros_type)
        except Exception as exc:  # rosbags raises several kinds on a malformed payload
            raise RosMessageError(f"{where}: not a CDR {ros_type} ({exc})") from None

    def _on_info(self, topic: str) -> Callable[[zenoh.Sample], None]:
        def on_info(sample: zenoh.Sample) -> None:
            key = str(sample.key_expr)
            try:
                with self._cond:
                    self._count(key, sample.attachment)
                    if topic in self._infos or self._started:
                        return
                    if key_type(key) != CAMERA_INFO_TYPE:
                        raise RosMessageError(f"{key}: {topic} carries {key_type(key)}, "
                                              f"expected {CAMERA_INFO_TYPE}")
                    msg = self._decode(sample.payload.to_bytes(), CAMERA_INFO_TYPE, key)
                    self._infos[topic] = (msg, key)
                    self._cond.notify_all()
            except Exception as exc:
                self._fail(exc)
        return on_info

    def _on_image(self, stream: int) -> Callable[[zenoh.Sample], None]:
        def on_image(sample: zenoh.Sample) -> None:
            key = str(sample.key_expr)
            try:
                ros_type = key_type(key)
                if ros_type not in IMAGE_TYPES:
                    raise RosMessageError(f"{key}: an image topic carrying {ros_type}, "
                                          f"expected one of {', '.join(IMAGE_TYPES)}")
                payload = sample.payload.to_bytes()
                stamp = header_stamp(payload, key)
                with self._cond:
                    self._count(key, sample.attachment)
                    if not self._started:
                        if stream == DEPTH and self._depth_scale is None:
                            msg = self._decode(payload, ros_type, key)
                            self._depth_scale = depth_image_scale(msg, key)
                            self._cond.notify_all()
                        return
                    pair = self._pairer.add(stream, stamp, (payload, ros_type, key))
                    if pair is not None:
                        # Under the lock: pairs leave in stamp order, as the cloud expects.
                        self._slot.put(pair)
            except Exception as exc:
                self._fail(exc)
        return on_image

    def _frame(self, colour: Message, depth: Message, stamp: float) -> Frame:
        camera = self.camera
        message = self._decode(*colour)
        # The camera's TF frame, for what the robot publishes back (edge/ros2_out.py).
        self.camera_frame_id = str(message.header.frame_id).lstrip("/")
        size = (camera.width, camera.height)
        rgb = colour_image(message, colour[2], size)
        raw = depth_image(self._decode(*depth), depth[2], camera.depth_scale, size)
        for image, where in ((rgb, colour[2]), (raw, depth[2])):
            if image.shape[:2] != (camera.height, camera.width):
                raise RosMessageError(f"{where}: image of {image.shape[1]} x {image.shape[0]} "
                                      f"pixels, the camera ({self.camera_source}) has "
                                      f"{camera.width} x {camera.height}")
        raw = _writable(raw)
        return Frame(-1, stamp, _writable(rgb), raw, camera.depth_to_metres(raw))

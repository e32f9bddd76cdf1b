"""The cloud's live topics served straight to the Foxglove app over Foxglove's WebSocket
protocol (``fleetslam cloud --foxglove PORT``; ``pip install 'fleetslam[foxglove]'``): no ROS
2, no bridge. Open Foxglove, "Open connection", ``ws://HOST:PORT``.

The messages are ROS 2 messages in CDR (Foxglove decodes them with the ``ros2msg`` schemas
sent along), the same as ``--ros2-out`` and run.mcap carry:

    /<robot>/pose        geometry_msgs/PoseStamped      each tracked frame, in <robot>/map,
                                                        stamped when the cloud tracked it
    /tf                  tf2_msgs/TFMessage             <robot>/map -> <robot>/camera
    /tf_static           tf2_msgs/TFMessage             map -> <robot>/map (joined robots)
    /map/global, /map/grid, /map/octomap, /map/constraints, /<robot>/global_path
                                                        each merge's (run_mcap.add_fleet_map)

Foxglove's protocol has no transient local: the latest of each latched topic is sent again
to a client when it subscribes. Every call only hands a message to the SDK (its server
thread sends), so a robot's session never waits for a viewer.
"""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from fleetslam.config import ViewConfig
from fleetslam.io.mcap_out import RosMessages
from fleetslam.ros2_out import cdr
from fleetslam.run_mcap import GLOBAL_FRAME, add_fleet_map, camera_frame, map_frame
from fleetslam.visualisation.live_view import NullView

log = logging.getLogger("fleetslam.view")

INSTALL_HINT = "pip install 'fleetslam[foxglove]' (the Foxglove SDK, foxglove-sdk)"


def _foxglove() -> Any:
    try:
        import foxglove
    except ImportError:
        raise RuntimeError(f"--foxglove needs the Foxglove SDK: {INSTALL_HINT}") from None
    return foxglove


class FoxgloveView(NullView):
    enabled = True

    def __init__(self, cfg: ViewConfig, port: int) -> None:
        fox = _foxglove()
        self._fox = fox
        # The definitions come from rosbags' store (the cloud extra has it).
        self._store = RosMessages("ROS2_JAZZY")
        self._channels: dict[str, Any] = {}
        self._latched: dict[str, bytes] = {}  # topic -> its latest message
        self._lock = threading.Lock()
        self._resend = threading.Event()
        self._closed = threading.Event()
        view = self

        class Listener(fox.ServerListener):  # type: ignore[misc, name-defined]
            def on_subscribe(self, client: Any, channel: Any) -> None:
                if channel.topic in view._latched:
                    view._resend.set()  # sent from our thread, not the server's

        self._server = fox.start_server(name="fleetslam", host=cfg.foxglove_host, port=port,
                                        server_listener=Listener())
        self.port = self._server.port
        self._thread = threading.Thread(target=self._resend_latched, daemon=True,
                                        name="foxglove-latched")
        self._thread.start()
        log.info("Foxglove: open ws://%s:%d in the Foxglove app", cfg.foxglove_host, self.port)

    def _channel(self, topic: str, typename: str) -> Any:
        channel = self._channels.get(topic)
        if channel is None:
            fox = self._fox
            schema = fox.Schema(name=typename, encoding="ros2msg",
                                data=self._store.definition(typename).encode())
            channel = self._channels[topic] = fox.Channel(topic, schema=schema,
                                                          message_encoding="cdr")
        return channel

    def _log(self, topic: str, typename: str, data: bytes, latched: bool = False) -> None:
        with self._lock:
            channel = self._channel(topic, typename)
            if latched:
                self._latched[topic] = data
        channel.log(data, log_time=time.time_ns())

    def _resend_latched(self) -> None:
        while not self._closed.is_set():
            if not self._resend.wait(0.5):
                continue
            self._resend.clear()
            with self._lock:
                latest = [(self._channels[t], d) for t, d in self._latched.items()]
            for channel, data in latest:
                channel.log(data, log_time=time.time_ns())

    # -- what the cloud tells its view ------------------------------------------------------

    def frame(self, robot: str, index: int, T_map_camera: np.ndarray, tracked: bool,
              is_keyframe: bool, split_point: int, cloud_ms: float) -> None:
        if not tracked:
            return
        now = time.time_ns()
        self._log(f"/{robot}/pose", cdr.POSE_STAMPED,
                  cdr.pose_stamped(now, map_frame(robot), T_map_camera))
        self._log("/tf", cdr.TF_MESSAGE, cdr.tf_message(
            [(now, map_frame(robot), camera_frame(robot), T_map_camera)]))

    def merged(self, T_global_map: dict[str, np.ndarray],
               constraints: list[tuple[np.ndarray, np.ndarray, bool | None]]) -> None:
        now = time.time_ns()
        self._log("/tf_static", cdr.TF_MESSAGE, cdr.tf_message(
            [(now, GLOBAL_FRAME, map_frame(robot), T)
             for robot, T in sorted(T_global_map.items())]), latched=True)

    def fleet_map(self, run_dir: Path, summary: dict[str, Any]) -> None:
        if not (summary.get("merge") or {}).get("members"):
            return
        messages = RosMessages("ROS2_JAZZY")
        add_fleet_map(messages, Path(run_dir), summary, time.time_ns())
        for _, _, topic, data in messages.messages:
            self._log(topic, messages.topics[topic][0], data, latched=True)

    def close(self) -> None:
        self._closed.set()
        self._thread.join(2.0)
        self._server.stop()

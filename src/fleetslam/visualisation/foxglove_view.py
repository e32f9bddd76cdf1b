"""The cloud's live topics served straight to the Foxglove app over Foxglove's WebSocket
protocol (``fleetslam cloud --foxglove PORT``; ``pip install 'fleetslam[foxglove]'``): no ROS
2, no bridge. Open Foxglove, "Open connection", ``ws://HOST:PORT``. The topics are
topic_view.py's, ROS 2 messages in CDR, which Foxglove decodes with the ``ros2msg`` schemas
the server sends along.

Foxglove's protocol has no transient local: the latest message of each latched topic is
sent again when a client subscribes to it (from this sink's own thread, not the server's).
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

from fleetslam.config import ViewConfig
from fleetslam.io.mcap_out import RosMessages
from fleetslam.visualisation.topic_view import STORES

log = logging.getLogger("fleetslam.view")

INSTALL_HINT = "pip install 'fleetslam[foxglove]' (the Foxglove SDK, foxglove-sdk)"


def _foxglove() -> Any:
    try:
        import foxglove
    except ImportError:
        raise RuntimeError(f"--foxglove needs the Foxglove SDK: {INSTALL_HINT}") from None
    return foxglove


class FoxgloveSink:
    def __init__(self, cfg: ViewConfig, port: int, distro: str = "jazzy") -> None:
        fox = _foxglove()
        self._fox = fox
        self._definitions = RosMessages(STORES[distro])  # rosbags' (the cloud extra has it)
        self._channels: dict[str, Any] = {}
        self._latched: dict[str, bytes] = {}  # topic -> its latest message
        self._lock = threading.Lock()
        self._resend = threading.Event()
        self._closed = threading.Event()
        sink = self

        class Listener(fox.ServerListener):  # type: ignore[misc, name-defined]
            def on_subscribe(self, client: Any, channel: Any) -> None:
                if channel.topic in sink._latched:
                    sink._resend.set()

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
                                data=self._definitions.definition(typename).encode())
            channel = self._channels[topic] = fox.Channel(topic, schema=schema,
                                                          message_encoding="cdr")
        return channel

    def publish(self, topic: str, typename: str, data: bytes, latched: bool) -> None:
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

    def close(self) -> None:
        self._closed.set()
        self._thread.join(2.0)
        self._server.stop()

"""``fleetslam cloud --foxglove PORT``: the Foxglove app's side of its WebSocket protocol
(a plain WebSocket client: advertise, subscribe, binary message data), checked against what
the cloud tracked and merged; messages decoded with rosbags from the schemas the server
advertises."""

from __future__ import annotations

import asyncio
import json
import struct
import threading

import numpy as np
import pytest

from fleetslam.config import Config

pytest.importorskip("foxglove")
websockets = pytest.importorskip("websockets")

SUBPROTOCOL = "foxglove.sdk.v1"
MESSAGE_DATA = 0x01
UNKNOWN = "Unknown channel ID:"


async def _subscribe(port: int, topics: list[str], wanted: int, timeout: float
                     ) -> tuple[dict[str, dict], dict[str, list[bytes]]]:
    """(advertised channel per topic, payloads per topic) once each topic has ``wanted``
    messages (or ``timeout``)."""
    got: dict[str, list[bytes]] = {t: [] for t in topics}
    channels: dict[str, dict] = {}
    async with websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL],
                                  max_size=None) as ws:
        by_sub: dict[int, str] = {}

        async def receive() -> None:
            while not all(len(v) >= wanted for v in got.values()):
                data = await ws.recv()
                if isinstance(data, str):
                    message = json.loads(data)
                    new = []
                    if message.get("op") == "advertise":
                        for channel in message["channels"]:
                            if channel["topic"] in got and channel["topic"] not in channels:
                                channels[channel["topic"]] = channel
                                sub = len(by_sub) + 1
                                by_sub[sub] = channel["topic"]
                                new.append({"id": sub, "channelId": channel["id"]})
                    elif message.get("op") == "status" and UNKNOWN in message.get("message", ""):
                        # foxglove-sdk 0.30 sends a new channel's advertise before it knows
                        # the channel itself: a subscription that comes back at once is
                        # refused. Ask again, as a client that reads the status would.
                        channel_id = int(message["message"].rsplit(":", 1)[1])
                        await asyncio.sleep(0.05)
                        new = [{"id": sub, "channelId": channel_id}
                               for sub, topic in by_sub.items()
                               if channels[topic]["id"] == channel_id]
                    if new:
                        await ws.send(json.dumps({"op": "subscribe", "subscriptions": new}))
                elif data[0] == MESSAGE_DATA:
                    sub, _ = struct.unpack_from("<IQ", data, 1)
                    got[by_sub[sub]].append(bytes(data[13:]))

        try:
            await asyncio.wait_for(receive(), timeout)
        except TimeoutError:
            pass
    return channels, got


def test_foxglove_gets_the_poses_and_a_late_client_the_merges_maps(tmp_path, synthetic_scene):
    from rosbags.typesys import Stores, get_typestore

    from fleetslam.cloud.server import CloudServer
    from fleetslam.datasets.tum import RgbdSequence
    from fleetslam.edge.robot import Robot
    from fleetslam.io.ply import read_ply
    from fleetslam.launch import free_endpoint
    from fleetslam.visualisation.views import open_view

    _, folders = synthetic_scene
    endpoint = free_endpoint()
    port = int(free_endpoint().rsplit(":", 1)[1])
    config = Config()
    view = open_view(config, None, False, port)
    server = CloudServer(config, tmp_path / "cloud", endpoint, view=view).start()
    live: dict = {}
    client = threading.Thread(target=lambda: live.update(zip(("channels", "got"), asyncio.run(
        _subscribe(port, ["/r0/pose", "/tf"], 20, 120.0)))), daemon=True)
    client.start()
    robots = [Robot(f"r{i}", RgbdSequence(f), f"r{i}", 3, config, endpoint, show_progress=False)
              for i, f in enumerate(folders)]
    try:
        threads = [threading.Thread(target=r.run, daemon=True) for r in robots]
        for t in threads:
            t.start()
        for t in threads:
            t.join(300)
        client.join(60)
        summary = server.merge()
        channels, late = asyncio.run(_subscribe(port, ["/map/global", "/map/grid"], 1, 20.0))
    finally:
        server.close()
    store = get_typestore(Stores.ROS2_JAZZY)
    assert live["channels"]["/r0/pose"]["encoding"] == "cdr"
    assert live["channels"]["/r0/pose"]["schemaName"] == "geometry_msgs/msg/PoseStamped"
    poses = [store.deserialize_cdr(d, "geometry_msgs/msg/PoseStamped")
             for d in live["got"]["/r0/pose"]]
    assert len(poses) >= 20 and all(p.header.frame_id == "r0/map" for p in poses)
    online = np.loadtxt(tmp_path / "cloud" / "r0" / "online.tum", comments="#", ndmin=2)
    first = poses[0].pose.position
    assert np.min(np.linalg.norm(online[:, 1:4] - [first.x, first.y, first.z], axis=1)) < 1e-9
    cloud = store.deserialize_cdr(late["/map/global"][-1], "sensor_msgs/msg/PointCloud2")
    points, _ = read_ply(tmp_path / "cloud" / summary["merge"]["global_map"])
    assert cloud.width == len(points) > 1000 and cloud.header.frame_id == "map"
    grid = store.deserialize_cdr(late["/map/grid"][-1], "nav_msgs/msg/OccupancyGrid")
    assert [grid.info.width, grid.info.height] == summary["merge"]["grid"]["size"]
    assert channels["/map/grid"]["schemaEncoding"] == "ros2msg"

"""An rmw_zenoh node made of plain Zenoh, as rmw_zenoh's docs/design.md and its sources
describe one (and as tests/test_ros2_out.py checks against zenoh-ros2-sdk, an independent
implementation):

- the node announces itself with a liveliness token (kind NN) and each publisher with its
  own (kind MP: topic, DDS type name, REP-2016 type hash, QoS), so ``ros2 node list`` and
  ``ros2 topic list`` on the graph show them;
- a publisher puts CDR (with its encapsulation header) on ``<domain>/<topic>/<type>/<hash>``
  with an attachment: its sequence number, the source time in ns and its 16-byte GID;
- a TRANSIENT_LOCAL publisher is a zenoh-ext AdvancedPublisher with a cache of ``depth``
  samples and publisher detection, which a late TRANSIENT_LOCAL subscriber queries (under
  ``<key>/@adv/pub/<zid>/...``), as rmw_zenoh's own publishers do;
- volatile publishers drop rather than block when the link is congested (rmw_zenoh's
  default), so a slow ROS 2 graph never holds up the caller.

Not done: services, parameters, the ``rosout`` topic and the type description service a
real rclcpp node also offers.
"""

from __future__ import annotations

import itertools
import logging
import os
import threading
import time

import zenoh
import zenoh.ext

from fleetslam.datasets.rmw_zenoh import (
    PUBLISHER,
    dds_type_name,
    endpoint_token,
    make_attachment,
    node_token,
    qos_chunk,
    topic_key,
)
from fleetslam.ros2_out.cdr import HUMBLE_TYPE_HASH, TYPE_HASHES

log = logging.getLogger("fleetslam.ros2_out")


class RosPublisher:
    """One topic's publisher; ``publish`` is thread-safe and never blocks on the graph."""

    def __init__(self, session: zenoh.Session, key: str, token_key: str,
                 transient_local: bool, depth: int) -> None:
        self.key = key
        self.gid = os.urandom(16)
        self.transient_local = transient_local
        if transient_local:
            self._pub = zenoh.ext.declare_advanced_publisher(
                session, key, cache=zenoh.ext.CacheConfig(max_samples=depth),
                publisher_detection=True)
        else:
            # express: sent at once, not batched with what follows (a pose is ~100 bytes;
            # bench/ros2_out.py: feedback -> ROS 2 p95 2.4-4.3 ms, 3.9-4.9 batched).
            self._pub = session.declare_publisher(
                key, congestion_control=zenoh.CongestionControl.DROP, express=True)
        self._token = session.liveliness().declare_token(token_key)
        self._sequence = itertools.count(1)
        # Zenoh's publisher may not be put to while it is undeclared (PyO3: "Already
        # borrowed"): both under this lock, and nothing is put once closed.
        self._lock = threading.Lock()
        self._closed = False

    def publish(self, cdr: bytes) -> bool:
        """Put one message; False once closed."""
        with self._lock:
            if self._closed:
                return False
            attachment = make_attachment(next(self._sequence), time.time_ns(), self.gid)
            self._pub.put(cdr, attachment=attachment)
            return True

    def close(self) -> None:
        with self._lock:
            self._closed = True
            for part in (self._token, self._pub):
                try:
                    part.undeclare()
                except zenoh.ZError:
                    pass  # the session is gone already


class RosNode:
    """A ROS 2 node on an open Zenoh session (``session``: a client of the robot's
    rmw_zenohd, or of a router standing in for it)."""

    # rmw_zenoh numbers a context's nodes and entities from 0 within its session; one
    # fleetslam node per session here.
    _NODE_ID = 0

    def __init__(self, session: zenoh.Session, name: str, namespace: str = "",
                 domain_id: int = 0, humble: bool = False) -> None:
        """``humble``: keys and tokens carry Humble's placeholder for the type hash."""
        self.session = session
        self.humble = humble
        self.name = name
        self.namespace = namespace
        self.domain_id = domain_id
        self.session_id = str(session.info.zid())
        self._entities = itertools.count(self._NODE_ID + 1)
        self._token = session.liveliness().declare_token(
            node_token(domain_id, self.session_id, self._NODE_ID, namespace, name))
        self.publishers: dict[str, RosPublisher] = {}

    def publisher(self, topic: str, ros_type: str, depth: int,
                  transient_local: bool = False, type_hash: str | None = None
                  ) -> RosPublisher:
        """A publisher of ``ros_type`` on ``topic``; its hash is ``cdr.TYPE_HASHES``' unless
        given (the cloud's messages: rosbags computes it)."""
        type_hash = HUMBLE_TYPE_HASH if self.humble else type_hash or TYPE_HASHES[ros_type]
        dds_type = dds_type_name(ros_type)
        token = endpoint_token(self.domain_id, self.session_id, self._NODE_ID,
                               next(self._entities), PUBLISHER, self.namespace, self.name,
                               topic, dds_type, type_hash, qos_chunk(depth, transient_local))
        pub = RosPublisher(self.session, topic_key(self.domain_id, topic, dds_type, type_hash),
                           token, transient_local, depth)
        self.publishers[topic] = pub
        return pub

    def close(self) -> None:
        for pub in self.publishers.values():
            pub.close()
        try:
            self._token.undeclare()
        except zenoh.ZError:
            pass

"""The operator's two requests to a cloud worker (``fleetslam status``, ``fleetslam merge``),
by request id: the status, built at most every STATUS_EVERY_S (a flood of requests costs one
build per interval, each still answered with its own id), and the merge, started only on the
worker that merges (merge_role.py), once per request (fleet_merge.py's MergeRequests).
"""

from __future__ import annotations

import dataclasses
import threading
import time

from fleetslam.cloud.coordination.placement_protocol import Placement
from fleetslam.cloud.merge.fleet_merge import MergeRequests
from fleetslam.cloud.merge.merge_role import MergeRole
from fleetslam.cloud.session.memory_budget import MB
from fleetslam.cloud.session.robot_session import OVER_BUDGET
from fleetslam.cloud.session.sessions import SessionTable
from fleetslam.transport import protocol

# A status answer is built at most this often; requests in between get the last one.
STATUS_EVERY_S = 0.2


class OperatorRequests:
    def __init__(self, worker_id: str, sessions: SessionTable, placement: Placement,
                 merging: MergeRole, merge_requests: MergeRequests) -> None:
        self.worker_id = worker_id
        self.sessions = sessions
        self.placement = placement
        self.merging = merging
        self.merge_requests = merge_requests
        self._lock = threading.Lock()
        self._cache: tuple[float, protocol.StatusReply] | None = None
        self.status_builds = 0

    def merge(self, rid: str | None) -> None:
        if not self.merging.is_merger():
            return  # one worker merges (merge_role.py)
        self.merge_requests.request(rid)

    def status(self, rid: str | None) -> protocol.StatusReply:
        """The status answer to request ``rid``."""
        now = time.monotonic()
        with self._lock:
            if self._cache is None or now - self._cache[0] >= STATUS_EVERY_S:
                self._cache = (now, self._build())
                self.status_builds += 1
            return dataclasses.replace(self._cache[1], id=rid)

    def _build(self) -> protocol.StatusReply:
        robots = {r: {"frames": s.counts()["frames"], "finished": s.finished is not None,
                      "worker": self.worker_id,
                      # Its memory budget: held now, and what it dropped unread.
                      "held_mb": round(s.budget.used / MB, 1),
                      "held_peak_mb": round(s.budget.peak / MB, 1),
                      "dropped_over_budget": sum(s.counts()[c] for c in OVER_BUDGET.values()),
                      # Its checkpoints: how many written, and their bytes (new chunks too).
                      "checkpoints": s.checkpoints.writes,
                      "checkpoint_bytes": s.checkpoints.bytes_written}
                  for r, s in self.sessions.now()}
        placement = self.placement
        return protocol.StatusReply(
            None, robots, self.merging.merger.status(), self.worker_id,
            placement.live_workers(), placement.table(), placement.elections)

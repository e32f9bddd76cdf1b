"""Which worker merges, and the keyframes its merger gets. One worker of the fleet runs the
map merger (merger_service.py): with a coordination service the holder of the merger's fenced grant
(fenced_placement.py), else the live one whose id sorts first. It takes its own sessions' keyframes
as they are checkpointed, the other workers publish theirs to it
(``fleet/cloud/keyframes/<robot>``), and a worker that becomes the merger (the last one died or
stopped) first takes every robot's keyframes from the store. A lone cloud is the merger."""

from __future__ import annotations

import logging

import numpy as np

from fleetslam.camera import Camera
from fleetslam.cloud.coordination.placement_protocol import Placement
from fleetslam.cloud.merge.fleet_frames import FleetFrames
from fleetslam.cloud.merge.merger_service import MergerService
from fleetslam.merging.saved_map import LoadedMap
from fleetslam.cloud.session.robot_session import Publish, RobotSession
from fleetslam.cloud.session.sessions import SessionTable
from fleetslam.config import Config
from fleetslam.transport import keys
from fleetslam.transport.protocol import Hello
from fleetslam.visualisation.live_view import NullView
from fleetslam.wire.merger_keyframes import (KeyframeSummary, decode_merger_keyframe,
                                             encode_merger_keyframe)

log = logging.getLogger("fleetslam.cloud")


class MergeRole:
    def __init__(self, config: Config, view: NullView, worker_id: str, sessions: SessionTable,
                 publish: Publish, placement: Placement,
                 frames: FleetFrames | None = None, loaded: LoadedMap | None = None
                 ) -> None:
        """``publish``: to the merging worker (droppable: a gap is filled from the store);
        ``placement``: says whether this worker merges; ``frames``: tells robots where the
        merger placed their maps. The table hands this role its robots and keyframes
        (``joined``, ``keyframe_sink``: SessionTable.hand_to)."""
        self.worker_id = worker_id
        self.sessions = sessions
        self.store = sessions.store
        self.publish = publish
        self.placement = placement
        self.merger = MergerService(config, view, self.keyframes_in_store, frames, loaded)
        self.loaded = loaded
        self._merging = False  # this worker runs the fleet's merger (see is_merger)

    def is_merger(self) -> bool:
        """The worker the placement names merges (the live worker whose id sorts first, or
        the holder of the merger's grant with a coordination service); a worker that
        becomes it (the last one died or stopped, or was fenced) first takes every other
        robot's keyframes from the store."""
        merging = self.placement.merges()
        if merging and not self._merging:
            # Its own robots' keyframes went to the merger that was; all robots are taken
            # (its own from their sessions here). No lock: callers may hold it.
            robots = sorted(set(self.store.robots_with_checkpoints()) | set(list(self.sessions)))
            if robots:
                log.info("worker %s merges now: robots %s from the store", self.worker_id,
                         ", ".join(robots))
                self.merger.rebuild_from_store(robots)
        self._merging = merging
        return merging

    def hello_problem(self, robot_id: str, hello: Hello) -> str | None:
        """Why a new robot's hello may not open a session against the loaded map (its
        camera is none of the map's; localisation only without a map), or None."""
        if self.loaded is None:
            return "localisation only, but this cloud has no saved map loaded (cloud --map)" \
                if hello.localise_only else None
        return self.loaded.camera_problem(robot_id, hello.camera)

    def joined(self, robot_id: str, hello: Hello, restored: RobotSession | None) -> None:
        """A session opened here (``restored``: from its checkpoint, with the keyframes it
        already has): the merger, if this worker runs it, takes the robot."""
        if self.is_merger():
            if restored is None:
                self.merger.add_robot(robot_id, hello.camera, localising=hello.localise_only)
            else:
                self.merger.add_robot(robot_id, hello.camera, restored.keyframes.all(),
                                      restored.keyframes.poses(), hello.localise_only)

    def keyframe_sink(self, summary: KeyframeSummary, poses: np.ndarray) -> None:
        """A session's new keyframe: to the merger here, or published for the worker that
        merges."""
        if self.is_merger():
            self.merger.submit(summary, poses)
        else:
            session = self.sessions.get(summary.robot)
            if session is not None:
                hello = session.state.hello
                self.publish(keys.merge_keyframe(summary.robot), encode_merger_keyframe(
                    hello.camera, summary, poses, hello.localise_only))

    def take_remote(self, data: bytes, robot_id: str) -> None:
        """Another worker's keyframe of ``robot_id`` (ValueError if it is not one)."""
        self.merger.submit_remote(*decode_merger_keyframe(data, robot_id))

    def keyframes_in_store(self, robot_id: str
                           ) -> tuple[Camera, list[KeyframeSummary], np.ndarray, bool] | None:
        """A robot's keyframes for the merger: its live session's here, else its checkpoint
        in the store (read only)."""
        session = self.sessions.live(robot_id) or self.sessions.stored(robot_id)
        if session is None:
            return None
        hello = session.state.hello
        return (hello.camera, session.keyframes.all(), session.keyframes.poses(),
                hello.localise_only)

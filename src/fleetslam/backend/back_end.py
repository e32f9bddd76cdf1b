"""The back-end of one robot: ORB-SLAM's Tracking, LocalMapping and LoopClosing as peers.

    every frame:  Match -> EstimatePose -> DecideKeyframe          (tracking.py)
    a keyframe:   -> LocalMapper: insert, fuse, cull, local BA     (local_mapping.py)
                  -> LoopCloser: query, verify, correct             (loop_closing.py)

All three read and update one ``BackEndState`` (state.py). In-line (one process, a robot at
point 6, the exactness tests) everything runs on the tracking thread in that order, so every
process computes the same poses. In a cloud, ``workers`` take local BA and the loop closer's
database query off the tracking thread; their answers land at the start of a later frame
(``poll``).

``RobotSlam`` (robot_slam.py) puts the front end's stages and these together: one robot's
SLAM from any offloading point.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from fleetslam.backend.jobs import duration_stats
from fleetslam.backend.local_mapping import LocalMapper
from fleetslam.backend.loop_closing import LoopCloser
from fleetslam.backend.places import make_database
from fleetslam.backend.state import BackEndState
from fleetslam.backend.tracking import DecideKeyframe, EstimatePose, Match
from fleetslam.backend.workers import LocalMappingPool, SessionWorkers
from fleetslam.camera import Camera
from fleetslam.config import Config
from fleetslam.pipeline.split import Stage
from fleetslam.pipeline.states import PosedFrame


def new_state(config: Config, camera: Camera) -> BackEndState:
    """A robot's back-end state before its first frame."""
    return BackEndState(config, camera, make_database(config.place_recognition))


class CloudBackEnd:
    """One robot's back-end (see the module's docstring). ``state``: a restored one (a
    checkpoint); ``workers``: the cloud's worker processes (None: all in-line)."""

    def __init__(self, config: Config, camera: Camera, state: BackEndState | None = None,
                 workers: LocalMappingPool | None = None) -> None:
        self.state = state if state is not None else new_state(config, camera)
        self.workers = SessionWorkers(workers) if workers is not None else None
        self.local_mapper = LocalMapper(self.state, self.workers)
        # A loop correction moves the whole map: local BA in flight lands first.
        self.loop_closer = LoopCloser(self.state, self.local_mapper.flush, self.workers)
        self.stages: list[Stage] = [Match(), EstimatePose(),
                                    DecideKeyframe(self._new_keyframe, self.local_mapper)]

    def _new_keyframe(self, posed: PosedFrame) -> np.ndarray:
        """Local mapping, then loop closing, for a new keyframe; its pose after them."""
        inserted = self.local_mapper.insert_keyframe(posed)
        # Local BA moved the keyframe: move the previous pose with it, so the constant
        # velocity model keeps its velocity (and again for a loop correction).
        self.state.correct_motion(inserted.correction)
        loop = self.loop_closer.close_loops(inserted.keyframe)
        if loop is not None:
            self.state.correct_motion(loop)
        return inserted.keyframe.T_world_camera.copy()

    def poll(self) -> None:
        """A frame boundary: what the workers answered meanwhile lands in the map now."""
        if self.workers is not None:
            self.loop_closer.poll()
            self.local_mapper.poll()

    def finish(self) -> None:
        """The last keyframes' loop queries and local BA belong in the final map."""
        if self.workers is not None:
            self.loop_closer.flush()
            self.local_mapper.flush()
            self.close()  # no query after the last

    def close(self) -> None:
        """The session ended: the workers forget it (its keyframe database in its worker)."""
        self.loop_closer.release()

    def summary(self) -> dict[str, Any]:
        """Loop closing and relocalisation counts and times, for summary.json."""
        state = self.state
        loops = state.loops
        return {
            "loops_accepted": sum(1 for e in loops.events if e["accepted"]),
            "loops_rejected_by_graph": sum(1 for e in loops.events if not e["accepted"]),
            "loop_queries": loops.queries, "candidates_verified": loops.candidates_verified,
            "verified_detections": loops.detections_total,
            "loop_query": duration_stats(loops.query_seconds),
            "loop_correction": duration_stats(loops.correction_seconds),
            "local_ba": duration_stats(state.local_ba_seconds),
            "local_mapping": self.local_mapping_summary(),
            "culled_keyframes": state.culled_keyframes,
            "keyframe_reasons": dict(state.keyframe_reasons),
            "relocalisations": state.relocalisations, "loss_events": state.loss_events,
            "pnp_fallbacks": state.pnp_fallbacks,
            "events": loops.events,
        }

    def local_mapping_summary(self) -> dict[str, Any]:
        """Where local BA ran and, in the workers, what became of the requests."""
        if self.workers is None:
            return {"mode": "inline"}
        return {"mode": "inline (worker failed)" if self.workers.broken else "async",
                **self.local_mapper.summary(), "loop_queries": self.loop_closer.summary()}

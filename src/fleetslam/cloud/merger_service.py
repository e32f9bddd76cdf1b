"""The cloud's map merger on its own thread: robot sessions hand it each new keyframe and go
on tracking; it queries the other robots' places, joins robots and keeps the global pose
graph. A slow query never holds up a robot's frames, and a failure on one keyframe is
logged and counted, never raised into a session.
"""

from __future__ import annotations

import logging
import queue
import threading
from typing import Any, Callable, TypeVar

import numpy as np

from fleetslam.camera import Camera
from fleetslam.config import Config
from fleetslam.merging.inter_robot import KeyframeSummary
from fleetslam.merging.merger import MapMerger

log = logging.getLogger("fleetslam.merge")

T = TypeVar("T")


class MergerService:
    def __init__(self, config: Config) -> None:
        self.merger = MapMerger(config)
        self.errors = 0
        self._lock = threading.Lock()
        self._queue: queue.Queue = queue.Queue()
        self._thread = threading.Thread(target=self._run, name="cloud-merger", daemon=True)
        self._thread.start()

    def add_robot(self, robot: str, camera: Camera,
                  keyframes: list[KeyframeSummary] | None = None,
                  poses: np.ndarray | None = None) -> None:
        """Register a robot; a session restored from its checkpoint brings the keyframes it
        already has (the merger is rebuilt from them after a cloud restart)."""
        self._queue.put(("robot", (robot, camera, keyframes or [], poses)))

    def submit(self, summary: KeyframeSummary, poses: np.ndarray) -> None:
        self._queue.put(("keyframe", (summary, poses)))

    def _run(self) -> None:
        while (item := self._queue.get()) is not None:
            kind, payload = item
            try:
                with self._lock:
                    if kind == "robot":
                        robot, camera, keyframes, poses = payload
                        self.merger.add_robot(robot, camera)
                        have = len(self.merger.robots[robot].keyframes)
                        for kf in keyframes[have:]:
                            self.merger.add_keyframe(kf, poses[: kf.keyframe + 1])
                        if poses is not None:
                            self.merger.update_poses(robot, poses)
                    elif kind == "keyframe":
                        self.merger.add_keyframe(*payload)
                    elif kind == "call":
                        payload()
            except Exception:
                self.errors += 1
                log.exception("merger: %s failed", kind)

    def drain(self, timeout: float) -> bool:
        """Wait until everything submitted so far is merged; False on timeout."""
        done = threading.Event()
        self._queue.put(("call", done.set))
        return done.wait(timeout)

    def locked(self, work: Callable[[MapMerger], T]) -> T:
        """Run ``work`` on the merger while no keyframe is being added."""
        with self._lock:
            return work(self.merger)

    def status(self) -> dict[str, Any]:
        status = self.locked(lambda m: m.status())
        status["errors"] = self.errors
        status["queued"] = self._queue.qsize()
        return status

    def close(self, timeout: float = 5.0) -> None:
        self._queue.put(None)
        self._thread.join(timeout)

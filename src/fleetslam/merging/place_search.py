"""Inter-robot place search, the merger's heaviest step: for a robot's new keyframe, ask every
other robot's keyframe database for candidates and verify them geometrically
(inter_robot.py); then index the keyframe for the keyframes to come.

``PlaceSearch`` does it in-line (one-process runs, the tests). ``PlaceSearchProcess`` (the
cloud's) runs a ``PlaceSearch`` in a process of its own at a lower priority: the search
holds Python's GIL for its numpy work and faiss's search, so on the merger's thread it
took the GIL from the robots tracking in the same worker (measured: 21 % of that worker's
GIL time with 8 robots at once, more than their tracking). Both give the same matches: a
search is a function of the keyframes indexed before it, seeded per keyframe.

If the process dies or misses its deadline, the search goes on in-line from the keyframes
kept here, and the log says so: a failed helper must not end the merge.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from typing import TYPE_CHECKING, Sequence

import numpy as np

from fleetslam.backend.place_recognition import ApproximateKeyframeDatabase, KeyframeDatabase
from fleetslam.backend.places import make_database
from fleetslam.backend.workers import start_background
from fleetslam.camera import Camera
from fleetslam.config import Config
from fleetslam.merging.inter_robot import PlaceMatch, verify_places
from fleetslam.wire.merger_keyframes import KeyframeSummary

if TYPE_CHECKING:
    from fleetslam.backend.vocabulary import BowDatabase

log = logging.getLogger("fleetslam.merge")


@dataclass
class _Robot:
    camera: Camera
    places: "KeyframeDatabase | ApproximateKeyframeDatabase | BowDatabase"
    keyframes: list[KeyframeSummary] = field(default_factory=list)


class PlaceSearch:
    """Each robot's keyframes and their place database; ``add_keyframe`` searches, then
    indexes."""

    def __init__(self, config: Config) -> None:
        self.config = config
        self.robots: dict[str, _Robot] = {}

    def add_robot(self, name: str, camera: Camera) -> None:
        if name not in self.robots:
            self.robots[name] = _Robot(camera, self._database())

    def _database(self) -> "KeyframeDatabase | ApproximateKeyframeDatabase | BowDatabase":
        pr, cfg = self.config.place_recognition, self.config.merge
        if cfg.place_index == "approximate" and pr.method == "nearest_neighbour":
            return ApproximateKeyframeDatabase(pr, cfg.place_index_exact_up_to,
                                               cfg.place_index_links, cfg.place_index_breadth)
        return make_database(pr)

    def add_keyframe(self, summary: KeyframeSummary, others: Sequence[str]
                     ) -> list[PlaceMatch]:
        """The verified matches of ``summary`` in the robots ``others`` (at most one per
        robot, in that order); then ``summary`` is indexed."""
        matches = [m for other in others if (m := self._find_place(summary, other)) is not None]
        self.index(summary)
        return matches

    def index(self, summary: KeyframeSummary) -> None:
        robot = self.robots[summary.robot]
        robot.keyframes.append(summary)
        robot.places.add(summary.keyframe, summary.features.descriptors)

    def _find_place(self, query: KeyframeSummary, other_name: str) -> PlaceMatch | None:
        other = self.robots[other_name]
        if not len(other.places):
            return None
        camera = self.robots[query.robot].camera
        for candidate in other.places.query(query.features.descriptors,
                                            top_k=self.config.merge.candidates):
            match = verify_places(query, camera, other.keyframes[candidate.key],
                                  other.camera, candidate.score, self.config)
            if match is not None:
                return match
        return None


# A match as it crosses the pipe: (place robot, place keyframe, T_place_query, score,
# RANSAC inliers, refined inliers); the keyframes themselves are on both sides already.
Found = tuple[str, int, np.ndarray, float, int, int]


def _serve(conn: Connection, config: Config, parent_pid: int) -> None:
    """The search process: requests from ``conn`` in order, until None or the cloud is
    gone."""
    start_background(parent_pid, 0)  # niced by the cloud as it started (see _start)
    search = PlaceSearch(config)
    while True:
        try:
            request = conn.recv()
        except (EOFError, OSError):  # the cloud is gone (killed: the pipe is reset)
            return
        if request is None:
            return
        kind, payload = request
        if kind == "robot":
            search.add_robot(*payload)
        elif kind == "keyframe":
            summary, others = payload
            conn.send([(m.place.robot, m.place.keyframe, m.T_place_query, m.score,
                        m.ransac_inliers, m.inliers)
                       for m in search.add_keyframe(summary, others)])


class PlaceSearchProcess:
    """A ``PlaceSearch`` in its own process (started at the first robot) at niceness
    ``nice``; a reply not back within ``timeout_s`` or a dead process turns the search
    in-line for good. Used from one thread (the merger's); ``close`` from any."""

    def __init__(self, config: Config, nice: int, timeout_s: float) -> None:
        self.config = config
        self.nice = nice
        self.timeout_s = timeout_s
        self._conn: Connection | None = None
        self._process: multiprocessing.process.BaseProcess | None = None
        # What the process was told, to rebuild the search in-line if it fails.
        self._robots: list[tuple[str, Camera]] = []
        self._keyframes: dict[str, list[KeyframeSummary]] = {}
        self._inline: PlaceSearch | None = None
        self._closed = False

    @property
    def inline(self) -> bool:
        return self._inline is not None

    def _start(self) -> Connection:
        if self._closed:
            raise OSError("the place search is closed")
        if self._conn is None:
            parent, child = multiprocessing.get_context("spawn").Pipe()
            self._process = multiprocessing.get_context("spawn").Process(
                target=_serve, args=(child, self.config, os.getpid()),
                name="fleetslam-place-search", daemon=True)
            self._process.start()
            # Niced from its first instruction, not once its imports are done: a second of
            # start-up CPU at tracking's priority made this worker look busy to placement.
            try:
                os.setpriority(os.PRIO_PROCESS, self._process.pid,
                               min(19, os.getpriority(os.PRIO_PROCESS, 0) + self.nice))
            except (AttributeError, OSError):  # not Linux, or gone already
                pass
            child.close()
            self._conn = parent
        return self._conn

    def add_robot(self, name: str, camera: Camera) -> None:
        if name in self._keyframes:
            return
        self._robots.append((name, camera))
        self._keyframes[name] = []
        if self._inline is not None:
            self._inline.add_robot(name, camera)
            return
        if self._closed:
            return
        try:
            self._start().send(("robot", (name, camera)))
        except (OSError, ValueError) as exc:
            self._fail(f"it could not be reached ({exc})")

    def add_keyframe(self, summary: KeyframeSummary, others: Sequence[str]
                     ) -> list[PlaceMatch]:
        self._keyframes[summary.robot].append(summary)
        if self._inline is None:
            found = self._ask(summary, others)
            if found is not None:
                return [PlaceMatch(summary, self._keyframes[robot][kf], T, score, ransac, n)
                        for robot, kf, T, score, ransac, n in found]
        if self._inline is None:  # closed: the cloud is stopping
            return []
        return self._inline.add_keyframe(summary, others)

    def _ask(self, summary: KeyframeSummary, others: Sequence[str]) -> list[Found] | None:
        """The process's answer, or None once it failed (then the search is in-line, and
        ``summary`` not yet indexed there)."""
        try:
            conn = self._start()
            conn.send(("keyframe", (summary, list(others))))
            if conn.poll(self.timeout_s):
                return conn.recv()
            reason = f"no answer within {self.timeout_s:.0f} s (merge.search_timeout_s)"
        except (OSError, EOFError, ValueError) as exc:
            reason = f"it failed ({exc!r})"
        self._fail(reason, pending=summary)
        return None

    def _fail(self, reason: str, pending: KeyframeSummary | None = None) -> None:
        if self._closed:  # the merger's thread was still at work when the cloud stopped
            return
        log.error("the merger's place search process: %s; searching in-line from now on",
                  reason)
        self._stop_process()
        search = PlaceSearch(self.config)
        for name, camera in self._robots:
            search.add_robot(name, camera)
            for kf in self._keyframes[name]:
                if kf is not pending:
                    search.index(kf)
        self._inline = search

    def _stop_process(self) -> None:
        conn, process, self._conn, self._process = self._conn, self._process, None, None
        if conn is not None:
            try:
                conn.send(None)
            except (OSError, ValueError):
                pass
            conn.close()
        if process is not None:
            process.join(2.0)
            if process.is_alive():
                process.kill()
                process.join(2.0)

    def close(self) -> None:
        """End the process (from any thread: a search still waiting gets no matches)."""
        self._closed = True
        self._stop_process()


Searcher = PlaceSearch | PlaceSearchProcess

"""The cloud's map merger on its own thread: robot sessions hand it each new keyframe and go
on tracking; it queries the other robots' places, joins robots and keeps the global pose
graph. A slow query never holds up a robot's frames, and a failure on one keyframe is
logged and counted, never raised into a session. The query (merging/place_search.py) is
asked for and its result taken when it comes: the merger's lock, which status and merges
take, is held only while the merger changes, never while a search runs.

With several cloud workers, one of them merges (merge_role.py: the holder of the merger's grant, or
the live worker whose id sorts first); the others publish their robots' keyframes to it
(wire/merger_keyframes.py), and a worker that becomes the merger takes every robot's keyframes from
the store first."""

from __future__ import annotations

import logging
import queue
import threading
import time
from typing import Any, Callable, TypeVar

import numpy as np

from fleetslam.camera import Camera
from fleetslam.cloud.merge.fleet_frames import FleetFrames
from fleetslam.config import Config
from fleetslam.mapping.map_frame import live_map_frame
from fleetslam.merging.fleet_map import FleetMap
from fleetslam.merging.global_map import largest_group
from fleetslam.merging.graph_solver import GraphSolver, GraphSolverProcess
from fleetslam.merging.saved_map import LoadedMap
from fleetslam.merging.merger import MapMerger
from fleetslam.merging.place_search import PlaceSearch, PlaceSearchProcess
from fleetslam.transforms import invert
from fleetslam.visualisation.live_view import NullView
from fleetslam.wire.merger_keyframes import KeyframeSummary

log = logging.getLogger("fleetslam.merge")

T = TypeVar("T")
# How often a drain looks again while searches are still out.
DRAIN_POLL_S = 0.05
# At most this share of the time goes to solving the graph for placements (and for the view):
# a fleet's graph grows with its robots, and placements every second re-solved it all the time.
SOLVE_SHARE = 0.25


# A robot's keyframes as the merger has them in the store: (camera, summaries, poses,
# localising only), or None (no checkpoint): what fills a gap in keyframes heard from
# another worker.
FromStore = Callable[[str], "tuple[Camera, list[KeyframeSummary], np.ndarray, bool] | None"]


class MergerService:
    def __init__(self, config: Config, view: NullView | None = None,
                 from_store: FromStore | None = None, frames: FleetFrames | None = None,
                 loaded: LoadedMap | None = None) -> None:
        """``frames``: tells each joined robot where its map lies (None: nobody is told);
        ``loaded``: a saved map, the fleet's first group (saved_map.py)."""
        cfg = config.merge
        self._queue: queue.Queue = queue.Queue()
        search = PlaceSearchProcess(config, cfg.search_nice, cfg.search_timeout_s,
                                    wake=lambda: self._queue.put(("searched", None))) \
            if cfg.search_process else PlaceSearch(config)
        # Started with the cloud: its imports, niced, are done before the first keyframe.
        search.start()
        # The fleet's map; its merger taken apart here (a search is asked without holding
        # the lock, its matches taken when they land).
        solver = GraphSolverProcess(cfg.solve_nice, cfg.solve_timeout_s) \
            if cfg.solve_process else GraphSolver()
        self.fleet = FleetMap(config, search, solver)
        self.merger = self.fleet.merger
        # The loaded map's robots as the global outputs need them (none without a map).
        self.saved_tracks = self.fleet.load(loaded) if loaded is not None else []
        self._from_store = from_store
        self.remote_gaps = 0  # keyframes that came after a gap, filled from the store
        self.errors = 0
        # The live view gets the global transforms and constraints at most every
        # view.global_every_s, on this thread (never on a robot's session).
        self.view = view or NullView()
        self._view_every_s = config.view.global_every_s
        self.grid = config.grid
        self._view_due = False
        self._view_at = -float("inf")
        self.frames = frames
        self._placing_every_s = config.merge.placement_every_s
        self._placing_due = False
        self._placed_at = -float("inf")
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._run, name="cloud-merger", daemon=True)
        self._thread.start()

    def add_robot(self, robot: str, camera: Camera,
                  keyframes: list[KeyframeSummary] | None = None,
                  poses: np.ndarray | None = None, localising: bool = False) -> None:
        """Register a robot; a session restored from its checkpoint brings the keyframes it
        already has (the merger is rebuilt from them after a cloud restart). ``localising``:
        it is placed in the loaded map, never moves nor extends it."""
        self._queue.put(("robot", (robot, camera, keyframes or [], poses, localising,
                                   time.monotonic())))

    def submit(self, summary: KeyframeSummary, poses: np.ndarray) -> None:
        self._queue.put(("keyframe", (summary, poses, time.monotonic())))

    def submit_remote(self, camera: Camera, summary: KeyframeSummary, poses: np.ndarray,
                      localising: bool = False) -> None:
        """A keyframe of a robot another worker serves: taken in order; one already held is
        skipped, and a gap (keyframes missed while this worker was not the merger, or
        lost) is filled from the robot's checkpoint in the store first."""
        self._queue.put(("remote", (camera, summary, poses, localising, time.monotonic())))

    def rebuild_from_store(self, robots: list[str]) -> None:
        """Take these robots' keyframes as their checkpoints in the store have them (a worker
        becoming the merger: the last one died or stopped)."""
        self._queue.put(("rebuild", (robots, time.monotonic())))

    def _take_robot(self, robot: str, camera: Camera, keyframes: list[KeyframeSummary],
                    poses: np.ndarray | None, localising: bool, asked: float) -> int:
        """Register the robot and take those of its keyframes not held yet; how many."""
        with self._lock:
            self.merger.add_robot(robot, camera, localising)
        have = len(self.merger.robots[robot].keyframes)
        for kf in keyframes[have:]:
            self._add(kf, poses[: kf.keyframe + 1], asked)
        return len(keyframes) - have

    def _add(self, summary: KeyframeSummary, poses: np.ndarray, asked: float) -> None:
        """A keyframe into the merger (under the lock), then its search asked for: its
        results come back as they are ready (``_take_results``); nothing here waits for
        one, nor holds the lock meanwhile (status and merges take it)."""
        with self._lock:
            self.merger.take_keyframe(summary, poses)
        self.merger.ask_search(summary, asked)

    def _take_results(self) -> None:
        # Under one hold of the lock: a status between a search's answer and its matches
        # would show the search done and its join not yet made.
        with self._lock:
            before = self._structure()
            for searched in self.merger.search.take_results():
                self.merger.take_matches(searched)
                self._view_due = True
            # Robots are told again only when a join or an inter-robot constraint changed
            # the graph: solving it for every new keyframe would cost the merger's thread
            # (20 ms a solve at 70 keyframes, growing with the map).
            self._placing_due |= self._structure() != before

    def _update_poses(self, robot: str, poses: np.ndarray) -> None:
        with self._lock:
            self.merger.update_poses(robot, poses)

    def _fill(self, robot: str, asked: float) -> None:
        loaded = self._from_store(robot) if self._from_store else None
        if loaded is not None and self._take_robot(robot, *loaded, asked) > 0:
            self._update_poses(robot, loaded[2])

    def _keyframe(self, summary: KeyframeSummary, poses: np.ndarray, arrival: float) -> None:
        """Keyframes in order: one held already (a rebuild from the store took it) only
        brings newer poses; a gap is filled from the store first."""
        if summary.keyframe > len(self.merger.robots[summary.robot].keyframes):
            self.remote_gaps += 1
            self._fill(summary.robot, arrival)
        have = len(self.merger.robots[summary.robot].keyframes)
        if summary.keyframe == have:
            self._add(summary, poses, arrival)
        elif summary.keyframe < have and len(poses) >= have:
            self._update_poses(summary.robot, poses)

    def _run(self) -> None:
        """This thread alone changes the merger; it holds the lock only while it does."""
        waits = ([self._view_every_s] if self.view.enabled else []) + \
            ([self._placing_every_s] if self.frames is not None else [])
        wait = min(waits) if waits else None
        while True:
            taken = True  # off the queue: task_done once merged (status counts it till then)
            try:
                item = self._queue.get_nowait()
            except queue.Empty:
                # Nothing new: a put-off place search (an in-line one) is done now.
                if self.merger.search.idle():
                    item, taken = ("tick", None), False
                else:
                    try:
                        item = self._queue.get(timeout=wait)
                    except queue.Empty:
                        # The view's last changes, when keyframes stop.
                        item, taken = ("tick", None), False
            if item is None:
                return
            kind, payload = item
            try:
                self._view_due |= kind in ("robot", "keyframe")
                if kind == "robot":
                    robot, camera, keyframes, poses, localising, asked = payload
                    self._take_robot(robot, camera, keyframes, poses, localising, asked)
                    if poses is not None:
                        self._update_poses(robot, poses)
                elif kind == "keyframe":
                    self._keyframe(*payload)
                elif kind == "remote":
                    camera, summary, poses, localising, arrival = payload
                    with self._lock:
                        self.merger.add_robot(summary.robot, camera, localising)
                    self._keyframe(summary, poses, arrival)
                elif kind == "rebuild":
                    robots, asked = payload
                    for robot in robots:
                        self._fill(robot, asked)
                elif kind == "call":
                    payload()
                self._take_results()
                if self._view_due and time.monotonic() - self._view_at >= self._every(
                        self._view_every_s):
                    self.show()
                self._place()
            except Exception:
                self.errors += 1
                log.exception("merger: %s failed", kind)
            finally:
                if taken:
                    self._queue.task_done()

    def _show(self) -> None:
        """Hand the view every robot's global transform and the inter-robot constraints
        (as lines between their keyframes, in the global frame). Under the lock."""
        if not self.view.enabled:
            return
        m = self.merger
        level = self._level(m)
        transforms = {name: level[name] @ m.solve_T_global_map(name) for name in m.robots}
        poses = m.solve_keyframe_poses()
        lines = []
        for c in m.constraints:
            q, p = c.match.query, c.match.place
            if q.keyframe < len(poses[q.robot]) and p.keyframe < len(poses[p.robot]):
                lines.append(((level[q.robot] @ poses[q.robot][q.keyframe])[:3, 3],
                              (level[p.robot] @ poses[p.robot][p.keyframe])[:3, 3], c.kept))
        # `map` is one group's frame: a loaded map's, else the largest (as a merge picks).
        fleet = largest_group(m, m.robots)[1] if m.robots else []
        self.view.merged(transforms, lines, fleet if len(fleet) > 1 else [])
        self._view_due = False
        self._view_at = time.monotonic()

    def _level(self, m: MapMerger) -> dict[str, np.ndarray]:
        """Each robot's T_map_graph: its group's level map frame while the robots run
        (map_frame.py: the anchor's mounting, else [grid] up; a merge finds the floor). A
        loaded map's group is in the map's frame, level already."""
        out = {}
        for anchor, members in m.components().items():
            if anchor == m.fixed_anchor:
                out.update({r: np.eye(4) for r in members})
                continue
            T_graph_map = live_map_frame(m.solve_T_global_map(anchor), m.robots[anchor].camera,
                                         self.grid)
            out.update({r: invert(T_graph_map) for r in members})
        return out

    def _every(self, every_s: float) -> float:
        """The least time between two placements (or views): ``every_s``, or longer when
        solving the graph for one took more than SOLVE_SHARE of it."""
        solved = self.merger.graph_seconds
        return max(every_s, solved[-1] / SOLVE_SHARE if solved else 0.0)

    def _structure(self) -> tuple[int, tuple[tuple[str, ...], ...]]:
        """What placements depend on: the inter-robot constraints and the groups."""
        m = self.merger
        return len(m.constraints), tuple(sorted(tuple(v) for v in m.components().values()))

    def _place(self) -> None:
        """Tell the joined robots where their maps lie, when something changed and at most
        every merge.placement_every_s; every placement again now and then."""
        if self.frames is None:
            return
        if self._placing_due and time.monotonic() - self._placed_at >= self._every(
                self._placing_every_s):
            self._placing_due = False
            self._placed_at = time.monotonic()
            self.frames.update(self.placements())
        self.frames.resend_due()

    def placements(self) -> dict[str, tuple[str, np.ndarray]]:
        """Where the graph puts each joined robot's map now: (its group, T_global_map in the
        group's level frame), what robots hear while they run (``placed``)."""

        def place(fleet: FleetMap) -> dict[str, tuple[str, np.ndarray]]:
            # A lone robot's map is its group's frame: nothing to tell, no graph to solve.
            joined = {r: anchor for anchor, members in fleet.groups().items()
                      if len(members) > 1 for r in members}
            level = self._level(fleet.merger)
            return {r: (anchor, level[r] @ fleet.solve_T_global_map(r))
                    for r, anchor in joined.items()}

        return self.locked(place)

    def show(self) -> None:
        """Hand the view the merger's state now (after a merge)."""
        self.locked(lambda _: self._show())

    def drain(self, timeout: float) -> bool:
        """Wait until everything submitted so far is merged, its searches too; False on
        timeout."""
        deadline = time.monotonic() + timeout
        while True:
            done = threading.Event()
            self._queue.put(("call", done.set))
            if not done.wait(max(deadline - time.monotonic(), 0.0)):
                return False
            if not self.merger.search.pending:
                return True
            if time.monotonic() >= deadline:
                return False
            time.sleep(DRAIN_POLL_S)

    def locked(self, work: Callable[[FleetMap], T]) -> T:
        """Run ``work`` on the fleet's map while no keyframe is being added."""
        with self._lock:
            return work(self.fleet)

    def status(self) -> dict[str, Any]:
        # Groups, keyframes not yet merged (queued or in hand) and searches not yet landed,
        # read under one hold of the lock: what is still to merge shows until its matches
        # have landed, so groups without it are final (the operator is told so).
        status = self.locked(lambda fleet: {**fleet.merger.status(),
                                            "queued": self._queue.unfinished_tasks,
                                            "searches_waiting": fleet.merger.search.pending})
        status["errors"] = self.errors
        status["remote_gaps"] = self.remote_gaps
        return status

    def close(self, timeout: float = 5.0) -> None:
        self._queue.put(None)
        self._thread.join(timeout)
        self.merger.search.close()
        self.merger.solver.close()

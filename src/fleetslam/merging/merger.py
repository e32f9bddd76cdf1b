"""The map merger: joins robots whose keyframes show the same places into one global frame,
while they run, and keeps one robust pose graph over all their keyframes.

Each robot starts alone, in its own map frame (its first camera). Every new keyframe is
queried against the other robots' keyframe databases and verified (inter_robot.py), and a
robot's keyframes are searched again in another robot's map that has doubled since, until
the two are joined (place_search.py), so a join does not depend on which robot came first. A
verified match implies a transform between the two robots' map frames; two robots join
only when ``merge.consistent_detections`` matches from different keyframes imply the same
transform (pairwise consistency, as PCM checks it). Weak or lone matches never join
anything; robots that share no place stay apart and are retried as keyframes arrive.

A joined group (component) lives in the map frame of its member whose id sorts first. Its pose graph has one
node per keyframe of every member: odometry edges from each robot's own latest keyframe
poses (known inliers) and one edge per inter-robot match. The matches that justified a
join are trusted; every later one is tested by GNC, so a wrong match is dropped, not merged.

No ground truth is read here: the merger sees only what robots' sessions computed.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from fleetslam.camera import Camera
from fleetslam.config import Config
from fleetslam.merging.graph_solver import GraphSolver
from fleetslam.merging.dense_constraint import DenseCloud, DenseRefinement, prepare, refine
from fleetslam.merging.constraint import Constraint
from fleetslam.merging.inter_robot import PlaceMatch
from fleetslam.merging.place_search import PlaceSearch, Searched, Searcher, pair_key
from fleetslam.merging.proximity import proximity_constraints
from fleetslam.wire.merger_keyframes import KeyframeSummary
from fleetslam.backend.pose_graph import PoseEdge
from fleetslam.transforms import invert, transforms_agree

log = logging.getLogger("fleetslam.merge")

# Graph node of keyframe k of the robot added i-th.
NODE_STRIDE = 1_000_000

# A keyframe's depth cloud in its own camera frame (N x 3), by robot and keyframe id; None
# when its images are not at hand.
KeyframeCloud = Callable[[str, int], "np.ndarray | None"]


@dataclass
class RobotRecord:
    name: str
    order: int  # position in arrival order (the graph's node block)
    camera: Camera
    keyframes: list[KeyframeSummary] = field(default_factory=list)
    poses: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))  # T_map_keyframe
    # The component (by its anchor robot) and this robot's map frame in the anchor's frame.
    anchor: str = ""
    T_anchor_map: np.ndarray = field(default_factory=lambda: np.eye(4))
    joined: dict[str, Any] | None = None  # how and when it joined its component


def _node(record: RobotRecord, keyframe: int) -> int:
    return record.order * NODE_STRIDE + keyframe


class MapMerger:
    def __init__(self, config: Config, search: Searcher | None = None,
                 solver: GraphSolver | None = None) -> None:
        self.config = config
        self.robots: dict[str, RobotRecord] = {}
        # Where the global pose graph is solved (in-line unless given).
        self.solver = solver if solver is not None else GraphSolver()
        # The robots' place databases and the search in them (in-line unless given).
        self.search = search if search is not None else PlaceSearch(config)
        # Verified matches not (yet) part of a join, per unordered robot pair.
        self.pending: dict[tuple[str, str], list[PlaceMatch]] = {}
        self.constraints: list[Constraint] = []
        self._pairs: set[tuple[tuple[str, int], ...]] = set()  # keyframe pairs matched
        self.events: list[dict[str, Any]] = []
        self.query_seconds: list[float] = []
        # Keyframes indexed with their search put off (the cloud's merger was behind), and
        # put-off searches done since.
        self.put_off = 0
        self.searched_late = 0
        self.graph_seconds: list[float] = []
        self.dense_seconds: list[float] = []
        # Global keyframe poses per robot from the last optimisation (None: stale).
        self._global: dict[str, np.ndarray] | None = None
        # A loaded map's group: its frame is kept whoever joins it (None: no map loaded).
        self.fixed_anchor: str | None = None
        self.saved: set[str] = set()  # the loaded map's robots (FS-HICP leaves them)
        # Localisation only: the loaded map's keyframes hold their poses in the graph too.
        self.hold_saved = False
        # Robots placed in the map that never move it (localisation only, per robot): the
        # graph places them after the rest, and the saved map leaves them out.
        self.localising: set[str] = set()
        # Robot -> frames and seconds from its first keyframe to the keyframe it had when its
        # group joined the loaded map (its first pose in the map's frame).
        self.entered_map: dict[str, dict[str, float]] = {}

    # -- input ----------------------------------------------------------------------------

    def add_robot(self, name: str, camera: Camera, localising: bool = False) -> None:
        """``localising``: the robot is placed in the map without moving or extending it."""
        if localising:
            self.localising.add(name)
        if name in self.robots:
            return
        self.robots[name] = RobotRecord(name, len(self.robots), camera, anchor=name)
        self.search.add_robot(name, camera)

    def add_saved_robot(self, name: str, camera: Camera, keyframes: list[KeyframeSummary],
                        poses: np.ndarray, anchor: str) -> None:
        """A robot of a loaded map: its keyframes at their poses in the map's frame, in the
        map's group (``anchor``'s) from the start, indexed for the other robots' searches
        (none of them searched: the map's robots are joined already)."""
        self.add_robot(name, camera)
        record = self.robots[name]
        record.keyframes = list(keyframes)
        record.poses = np.array(poses, np.float64).reshape(-1, 4, 4)
        record.anchor, record.T_anchor_map = anchor, np.eye(4)
        record.joined = {"component": anchor, "via": ["the loaded map"], "frames": {},
                         "matches": 0}
        for summary in keyframes:
            self.search.submit(summary, [], time.monotonic())
        self.search.take_results()  # indexed only
        self.fixed_anchor = anchor
        self.saved.add(name)
        self._global = None

    def add_saved_constraint(self, query: KeyframeSummary, place: KeyframeSummary,
                             T_place_query: np.ndarray, information: np.ndarray | None,
                             kept: bool | None) -> None:
        """An inter-robot edge of a loaded map, as its graph held it (refined already)."""
        T = np.asarray(T_place_query, np.float64)
        dense = DenseRefinement(information is not None, "" if information is not None
                                else "the loaded map's edge was not refined", T,
                                information, 0.0, 0.0, 0.0, 0, 0.0)
        match = PlaceMatch(query, place, T, 0.0, 0, 0)
        self._pairs.add(pair_key(query, place))
        self.constraints.append(Constraint(match, trusted=True, kept=kept, dense=dense))
        self._global = None

    def update_poses(self, robot: str, poses: np.ndarray) -> None:
        """The robot's latest keyframe poses (local BA and loop closing move them)."""
        record = self.robots[robot]
        record.poses = np.array(poses, dtype=np.float64).reshape(-1, 4, 4)
        self._global = None

    def add_keyframe(self, summary: KeyframeSummary, poses: np.ndarray
                     ) -> list[dict[str, Any]]:
        """Take a robot's new keyframe (and its latest keyframe poses) and look for it in
        the other robots' maps. Returns the join events it caused (with an in-line search;
        a search process's results come later, through ``take_matches``)."""
        self.take_keyframe(summary, poses)
        self.ask_search(summary, time.monotonic())
        return [e for searched in self.search.take_results()
                for e in self.take_matches(searched)]

    def take_keyframe(self, summary: KeyframeSummary, poses: np.ndarray) -> None:
        """A robot's new keyframe and its latest keyframe poses, before its search."""
        record = self.robots[summary.robot]
        if summary.keyframe != len(record.keyframes):
            raise ValueError(f"robot {summary.robot}: keyframe {summary.keyframe} arrived, "
                             f"expected {len(record.keyframes)}")
        record.keyframes.append(summary)
        self.update_poses(summary.robot, poses)

    def ask_search(self, summary: KeyframeSummary, asked: float) -> None:
        """Ask for the keyframe's search in the other robots' maps, and the catch-up of those
        not joined with its robot (it arrived at ``asked``: one that waited beyond
        merge.search_behind_s is indexed at once, its search put off). Only the search
        changes: the cloud asks without holding the merger."""
        others = [name for name in self.robots if name != summary.robot] \
            if self.config.merge.enabled else []
        anchor = self.robots[summary.robot].anchor
        apart = [name for name in others if self.robots[name].anchor != anchor]
        self.search.submit(summary, others, asked, apart)

    def take_matches(self, searched: Searched) -> list[dict[str, Any]]:
        """A keyframe's search results into the merger; the join events they caused."""
        self.put_off += not searched.searched
        self.searched_late += searched.late
        if searched.seconds is not None:
            self.query_seconds.append(searched.seconds)
        events: list[dict[str, Any]] = []
        for match in searched.matches:
            # A pair counts once: a search rebuilt in-line after its process failed may
            # find again what the process had found.
            if (key := pair_key(match.query, match.place)) in self._pairs:
                continue
            self._pairs.add(key)
            event = self._consider(match)
            if event is not None:
                events.append(event)
        return events

    # -- joining ----------------------------------------------------------------------------

    def implied(self, match: PlaceMatch) -> np.ndarray:
        """T_mapPlace_mapQuery the match implies, from the robots' current keyframe poses."""
        q, p = self.robots[match.query.robot], self.robots[match.place.robot]
        return p.poses[match.place.keyframe] @ match.T_place_query @ invert(
            q.poses[match.query.keyframe])

    def _consider(self, match: PlaceMatch) -> dict[str, Any] | None:
        q, p = self.robots[match.query.robot], self.robots[match.place.robot]
        if q.anchor == p.anchor:
            # Already one frame: a further constraint, tested by GNC on the graph.
            self.constraints.append(Constraint(match, trusted=False))
            self._global = None
            return None
        pair = tuple(sorted((q.name, p.name)))
        found = self.pending.setdefault(pair, [])  # type: ignore[arg-type]
        found.append(match)
        agreeing = self._consistent_set(found)
        if len(agreeing) < self.config.merge.consistent_detections:
            return None
        return self._join(agreeing, found)

    def _as_pair_transform(self, match: PlaceMatch, first: str) -> tuple[np.ndarray, np.ndarray]:
        """(T_mapFirst_mapOther implied by ``match``, the point where it was seen, in the
        other robot's map)."""
        T = self.implied(match)  # T_mapPlace_mapQuery
        if match.place.robot == first:
            at = self.robots[match.query.robot].poses[match.query.keyframe][:3, 3]
            return T, at
        at = self.robots[match.place.robot].poses[match.place.keyframe][:3, 3]
        return invert(T), at

    def _consistent_set(self, matches: list[PlaceMatch]) -> list[PlaceMatch]:
        """The largest group of matches that all imply the same transform between the two
        maps, found greedily from the best-supported one. Each match is a different pair of
        keyframes (a pair is verified once), so every member is an observation of its
        own."""
        cfg = self.config.loop_closing
        first = min(matches[0].query.robot, matches[0].place.robot)
        implied = [self._as_pair_transform(m, first) for m in matches]

        def agree(i: int, j: int) -> bool:
            return transforms_agree(implied[i][0], implied[j][0], implied[j][1],
                                    cfg.consistency_rotation_deg,
                                    cfg.consistency_translation_m) and \
                transforms_agree(implied[i][0], implied[j][0], implied[i][1],
                                 cfg.consistency_rotation_deg, cfg.consistency_translation_m)

        n = len(matches)
        support = [[j for j in range(n) if agree(i, j)] for i in range(n)]
        best: list[int] = []
        for i in sorted(range(n), key=lambda i: -len(support[i])):
            group = [i]
            for j in support[i]:
                if j != i and all(agree(j, g) for g in group):
                    group.append(j)
            if len(group) > len(best):
                best = group
                if len(best) == n:
                    break
        return [matches[g] for g in best]

    def _join(self, agreeing: list[PlaceMatch], found: list[PlaceMatch]) -> dict[str, Any]:
        newest = agreeing[-1]
        q, p = self.robots[newest.query.robot], self.robots[newest.place.robot]
        # The group that keeps its frame: the one whose anchor's id sorts first (not the
        # first to arrive, so the global frame does not depend on network timing).
        # A loaded map's group keeps its frame whoever joins it.
        keep, absorb = (p, q) if (p.anchor != self.fixed_anchor, p.anchor) \
            <= (q.anchor != self.fixed_anchor, q.anchor) else (q, p)
        T_place_query = self.implied(newest)
        T_keep_absorb = T_place_query if keep is p else invert(T_place_query)  # map to map
        # absorbed robot's map -> keeping robot's map -> keeping anchor; and every member of
        # the absorbed component through its own anchor.
        T_anchorK_anchorZ = keep.T_anchor_map @ T_keep_absorb @ invert(absorb.T_anchor_map)
        old_anchor = absorb.anchor
        members = [r for r in self.robots.values() if r.anchor == old_anchor]
        for r in members:
            r.T_anchor_map = T_anchorK_anchorZ @ r.T_anchor_map
            r.anchor = keep.anchor
            if keep.anchor == self.fixed_anchor and r.keyframes and r.name not in self.saved:
                first, now = r.keyframes[0], r.keyframes[-1]
                self.entered_map[r.name] = {"frames": now.frame_index - first.frame_index,
                                            "seconds": now.timestamp - first.timestamp}
        for m in agreeing:
            self.constraints.append(Constraint(m, trusted=True, kept=True))
        found[:] = [m for m in found if m not in agreeing]
        event = {
            "type": "join", "robots": sorted([q.name, p.name]),
            "anchor": keep.anchor, "absorbed": sorted(r.name for r in members),
            "matches": len(agreeing),
            "query_robot": q.name, "query_frame": newest.query.frame_index,
            "place_robot": p.name, "place_frame": newest.place.frame_index,
            "keyframes": {q.name: len(q.keyframes), p.name: len(p.keyframes)},
        }
        # Every robot that was alone until now records the join that brought it in.
        for r in self.robots.values():
            if r.anchor == keep.anchor and r.joined is None:
                r.joined = {"component": keep.anchor, "via": event["robots"],
                            "frames": {q.name: newest.query.frame_index,
                                       p.name: newest.place.frame_index},
                            "matches": len(agreeing)}
        self.events.append(event)
        self._global = None
        log.info("robots %s and %s joined (%d consistent matches; %s frame %d sees %s frame %d)",
                 q.name, p.name, len(agreeing), q.name, newest.query.frame_index, p.name,
                 newest.place.frame_index)
        return event

    # -- dense refinement ---------------------------------------------------------------------

    def refine_constraints(self, cloud_of: KeyframeCloud) -> int:
        """Refine every constraint not refined yet whose two keyframes' depth clouds are at
        hand (merging/dense_constraint.py), then add the depth edges between joined robots'
        keyframes the refined graph puts near each other (merging/proximity.py; off with
        dense_refine too); how many registrations were tried. A refused refinement leaves
        the feature edge as it was, and GNC still judges every untrusted edge."""
        if not self.config.merge.dense_refine:
            return 0
        tried = 0
        ready: dict[tuple[str, int], DenseCloud | None] = {}

        def cloud(robot: str, keyframe: int) -> DenseCloud | None:
            # Prepared once per keyframe: a keyframe often takes part in several constraints.
            if (robot, keyframe) not in ready:
                points = cloud_of(robot, keyframe)
                ready[robot, keyframe] = None if points is None \
                    else prepare(points, self.config.merge)
            return ready[robot, keyframe]

        for c in self.constraints:
            if c.dense is not None:
                continue
            m = c.match
            start = time.perf_counter()  # with the clouds' preparation, where this does it
            place = cloud(m.place.robot, m.place.keyframe)
            query = cloud(m.query.robot, m.query.keyframe)
            if place is None or query is None:
                continue
            c.dense = refine(place, query, m.T_place_query, self.config.merge)
            self.dense_seconds.append(time.perf_counter() - start)
            tried += 1
            if not c.dense.accepted:
                log.info("dense refinement of %s frame %d ~ %s frame %d refused: %s",
                         m.query.robot, m.query.frame_index, m.place.robot,
                         m.place.frame_index, c.dense.reason)
        if tried:
            self._global = None  # the proximity search starts from the refined graph
        if self.config.merge.proximity_constraints:
            found, seconds = proximity_constraints(
                [m for m in self.components().values() if len(m) > 1],
                self.solve_keyframe_poses(),
                {name: r.keyframes for name, r in self.robots.items()}, self.saved,
                self._pairs, cloud, self.config.merge)
            self.constraints.extend(found)
            self.dense_seconds.extend(seconds)
            if seconds:
                self._global = None
            tried += len(seconds)
        return tried

    # -- the global pose graph ------------------------------------------------------------------

    def components(self) -> dict[str, list[str]]:
        """Anchor -> members (by id)."""
        out: dict[str, list[str]] = {}
        for r in sorted(self.robots.values(), key=lambda r: r.name):
            out.setdefault(r.anchor, []).append(r.name)
        return out

    def solve_keyframe_poses(self) -> dict[str, np.ndarray]:
        """Every robot's keyframe poses in its component's frame (K x 4 x 4), from the pose
        graph (re-optimised if anything changed since)."""
        if self._global is None:
            self._global = self._optimise()
        return self._global

    def _optimise(self) -> dict[str, np.ndarray]:
        out = {r.name: r.T_anchor_map @ r.poses for r in self.robots.values()}
        for anchor, members in self.components().items():
            if len(members) < 2:
                continue
            start = time.perf_counter()
            records = [self.robots[m] for m in members]
            # First the robots that make the map (a loaded map moves only when one of them
            # extends it); then the robots localising only, with the map held: they are
            # placed in it and never move it.
            making = [r for r in records if r.name not in self.localising]
            held = {r.name for r in making if self.hold_saved and r.name in self.saved}
            if len(making) > 1 and len(held) < len(making) and any(
                    r.name not in self.saved for r in making):
                self._solve(anchor, making, held, out)
            if len(making) < len(records):
                self._solve(anchor, records, {r.name for r in making}, out)
            self.graph_seconds.append(time.perf_counter() - start)
        return out

    def _solve(self, anchor: str, records: list[RobotRecord], held: set[str],
               out: dict[str, np.ndarray]) -> None:
        """The pose graph of ``records`` (odometry, and the constraints among them) from
        and into ``out``; the keyframes of ``held`` robots, and the group anchor's first,
        stay where they are."""
        cfg = self.config.merge
        names = {r.name for r in records}
        values: dict[int, np.ndarray] = {}
        edges: list[PoseEdge] = []
        odometry = (np.deg2rad(cfg.odometry_sigma_rotation_deg),
                    cfg.odometry_sigma_translation_m)
        for r in records:
            T = out[r.name]
            for k in range(len(T)):
                values[_node(r, k)] = T[k]
                if k:
                    edges.append(PoseEdge(_node(r, k - 1), _node(r, k),
                                          invert(r.poses[k - 1]) @ r.poses[k],
                                          "odometry", odometry))
        inter = (np.deg2rad(cfg.inter_sigma_rotation_deg), cfg.inter_sigma_translation_m)
        used = [c for c in self.constraints if c.match.query.robot in names
                and c.match.place.robot in names
                and not (c.match.query.robot in held and c.match.place.robot in held)]
        for c in used:
            m = c.match
            edges.append(PoseEdge(_node(self.robots[m.place.robot], m.place.keyframe),
                                  _node(self.robots[m.query.robot], m.query.keyframe),
                                  c.T_place_query, "loop", inter, trusted=c.trusted,
                                  information=c.information))
        # Nothing held: the group's frame is its anchor's first keyframe (or, the anchor
        # localising only and placed after, the first robot's).
        fixed = [_node(r, k) for r in records if r.name in held for k in range(len(r.poses))] \
            or [_node(self.robots[anchor] if anchor in names else records[0], 0)]
        result = self.solver.solve(values, edges, fixed, odometry[0], odometry[1])
        for c, kept in zip(used, result.loop_inliers):
            c.kept = kept
        for r in records:
            if r.name not in held:
                out[r.name] = np.array([result.poses[_node(r, k)]
                                        for k in range(len(r.poses))]).reshape(-1, 4, 4)

    def solve_T_global_map(self, robot: str) -> np.ndarray:
        """Where the graph puts the robot's map frame (its first keyframe's camera, as the
        map frame is the first camera) in its component's frame."""
        r = self.robots[robot]
        poses = self.solve_keyframe_poses()[robot]
        if not len(poses):
            return r.T_anchor_map.copy()
        return poses[0] @ invert(r.poses[0])

    def status(self) -> dict[str, Any]:
        """Per robot: keyframes, its component (anchor), whether and how it joined."""
        return {
            "components": self.components(),
            "robots": {r.name: {"keyframes": len(r.keyframes), "anchor": r.anchor,
                                "joined": r.joined}
                       for r in self.robots.values()},
            "constraints": len(self.constraints),
            "constraints_rejected": sum(c.kept is False for c in self.constraints),
            "pending_matches": {f"{a}+{b}": len(v) for (a, b), v in self.pending.items()},
            "keyframes_not_searched": self.put_off - self.searched_late,  # not yet
            "keyframes_searched_late": self.searched_late,
            "events": self.events,
        }

"""The merge a client asks for (``fleetslam merge``): the global outputs of the finished
robots, every worker's (global trajectories, map, OctoMap, summary.json; outputs.py keeps
the summary's schema), run.mcap (run_mcap.py) and the run report. MergeRequests answers
each request id once: a client resends its request until the reply arrives.
"""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path
from typing import Any

from fleetslam.cloud.coordination.placement_protocol import Placement
from fleetslam.cloud.merge.merger_service import MergerService
from fleetslam.cloud.session.replies import Publish
from fleetslam.cloud.session.session_outputs import FinishedMap
from fleetslam.cloud.session.sessions import SessionTable
from fleetslam.config import Config
from fleetslam.outputs import write_summary
from fleetslam.run_summary import RunSummary
from fleetslam.run_mcap import write_run_mcap
from fleetslam.transport import keys, protocol

log = logging.getLogger("fleetslam.cloud")

# A merge request still running, and how many answered merge requests are remembered (so
# a resent request gets the reply again instead of a second merge).
MERGE_RUNNING = b""
MERGES_REMEMBERED = 16


class NothingToMerge(RuntimeError):
    """A merge asked for before any robot finished: told to the client, not a failure."""


class MergeRequests:
    def __init__(self, fleet_merge: FleetMerge, publish: Publish) -> None:
        """``fleet_merge``: merges and returns the summary (raises if it cannot)."""
        self.fleet_merge = fleet_merge
        self.publish = publish
        self._replies: dict[str, bytes] = {}
        self._lock = threading.Lock()

    def request(self, rid: str | None) -> None:
        """Start a merge, unless this request id already did: a client resends its request
        until the reply arrives, and a resent merge must not merge again."""
        with self._lock:
            known = self._replies.get(rid) if rid is not None else None
            if known is None and rid is not None:
                self._replies[rid] = MERGE_RUNNING
                while len(self._replies) > MERGES_REMEMBERED:
                    self._replies.pop(next(iter(self._replies)))
        if known == MERGE_RUNNING:
            return  # its reply comes when it is done
        if known is not None:
            self.publish(keys.CLOUD_REPLY, known)  # the reply was lost: send it again
            return
        # Merging takes seconds: not on Zenoh's callback thread.
        threading.Thread(target=self._merge_and_reply, args=(rid,), daemon=True).start()

    def _merge_and_reply(self, rid: str | None) -> None:
        try:
            reply = protocol.encode(protocol.Merged(rid, self.fleet_merge.merge()))
        except NothingToMerge as exc:
            log.warning("merge asked for: %s", exc)
            reply = protocol.encode(protocol.Error.of(protocol.Code.FAILED, str(exc), id=rid))
        except Exception as exc:
            log.exception("merge failed")
            reply = protocol.encode(protocol.Error.of(protocol.Code.FAILED,
                                                      f"merge failed: {exc}", id=rid))
        if rid is not None:
            with self._lock:
                self._replies[rid] = reply
        self.publish(keys.CLOUD_REPLY, reply)


class FleetMerge:
    def __init__(self, config: Config, out_dir: Path, sessions: SessionTable,
                 merger: MergerService, placement: Placement) -> None:
        """``placement``: whether this worker still holds the merger's role (with a
        coordination service, its fenced grant): asked before each output is written."""
        self.config = config
        self.out_dir = out_dir
        self.sessions = sessions
        self.merger = merger
        self.placement = placement

    def _still_merger(self, what: str) -> None:
        # A worker fenced mid-merge stops before its next output: another worker merges now.
        if not self.placement.merges():
            raise RuntimeError(f"this worker is no longer the fleet's merger (fenced): "
                               f"{what} not written; ask again")

    def merge(self, timeout_s: float = 300.0) -> dict[str, Any]:
        """Write the global outputs of the finished robots (global trajectories, map, OctoMap)
        and summary.json; return the summary."""
        start = time.perf_counter()
        if not self.merger.drain(timeout_s):
            raise RuntimeError(f"the merger has not caught up with the robots' keyframes "
                               f"within {timeout_s:.0f} s; ask again")
        here = self.sessions.now()
        elsewhere, unfinished = self._elsewhere({robot_id for robot_id, _ in here})
        unfinished.update({robot_id: f"not finished: its stream has not ended "
                                     f"({s.state.counts['frames']} frames tracked so far)"
                           for robot_id, s in here if not s.finished})
        finished = sorted([*(s.finished for _, s in here if s.finished), *elsewhere],
                          key=lambda f: f.robot_id)
        if not self.merger.drain(timeout_s):
            raise RuntimeError(f"the merger has not taken the other workers' robots within "
                               f"{timeout_s:.0f} s; ask again")
        if not finished:
            raise NothingToMerge("no robot has finished yet, so there is nothing to merge (a "
                                 "robot finishes at the end of its stream; `fleetslam status` "
                                 "lists the robots this cloud serves)")
        self._still_merger("the global map")
        global_map = self.merger.locked(lambda fleet: fleet.build_outputs(
            [f.track for f in finished] + self.merger.saved_tracks, self.out_dir))
        if self.merger.frames is not None:
            # Each member robot still connected hears summary.json's transform.
            self.merger.frames.update({m: (global_map.anchor, T) for m, T in
                                       global_map.T_global_map.items()}, final=True)
        merge = self.merger.locked(lambda fleet: fleet.summary(global_map))
        merge["robots"] = {k: v for k, v in merge["robots"].items()
                           if k in {f.robot_id for f in finished}}
        merge["not_merged"] = {**unfinished, **merge.get("not_merged", {})}
        for robot, why in unfinished.items():
            log.warning("merge: robot %s left out: %s", robot, why)
        summary = RunSummary([f.summary for f in finished], merge, self.config,
                             time.perf_counter() - start).to_dict()
        self._still_merger("the saved map")
        saved = self.merger.locked(lambda fleet: fleet.save(self.out_dir / "map", global_map))
        if saved is not None:  # None: every robot localised only (the map is not extended)
            summary["map"] = saved
        self._still_merger("summary.json")
        if self.config.outputs.mcap:
            summary["mcap"] = self._write_mcap(summary)
        write_summary(self.out_dir, summary)
        self.merger.show()
        self._publish(summary)
        log.info("merged %d maps in %.1f s", len(finished), time.perf_counter() - start)
        page = self._write_report()
        # For the client (not in summary.json): where the files are on this machine.
        summary["outputs"] = {"folder": str(self.out_dir.resolve()),
                              "report": str(page.relative_to(self.out_dir)) if page else None}
        return summary

    def _publish(self, summary: dict[str, Any]) -> None:
        """The merge's maps to the live views (a ROS 2 graph, Foxglove); like the report, a
        failure costs them, not the merge."""
        try:
            self.merger.view.fleet_map(self.out_dir, summary)
        except Exception:
            log.exception("the merge's maps could not be published")

    def _elsewhere(self, here: set[str]) -> tuple[list[FinishedMap], dict[str, str]]:
        """The robots other workers serve (or served), read from the store: the finished
        ones (the merger takes their keyframes as a restored session hands them over), and
        why each of the others is left out."""
        found, unfinished = [], {}
        for robot_id in self.sessions.store.robots_with_checkpoints():
            if robot_id in here:
                continue
            session = self.sessions.stored(robot_id)
            if session is None:
                continue
            if not session.state.ended:
                unfinished[robot_id] = "not finished: its stream has not ended (its " \
                                       "checkpoint says so)"
                continue
            state = session.state
            self.merger.add_robot(robot_id, state.hello.camera, session.keyframes.all(),
                                  session.keyframes.poses(), state.hello.localise_only)
            found.append(session.outputs.finished_map())
        return found, unfinished

    def _write_mcap(self, summary: dict[str, Any]) -> str | None:
        """``run.mcap`` of what was just merged (its name); like the report, a failure costs
        the file, not the merge."""
        start = time.perf_counter()
        try:
            path = write_run_mcap(self.out_dir, summary)
        except Exception:
            log.exception("run.mcap could not be written")
            return None
        log.info("mcap: %s (%.1f MB in %.2f s)", path, path.stat().st_size / 1e6,
                 time.perf_counter() - start)
        return path.name

    def _write_report(self) -> Path | None:
        """The run report of what was just merged, in the cloud's folder, without ground
        truth (the cloud never reads it); its page, None if it failed (a plot that fails
        costs the report, not the merge)."""
        from fleetslam.reporting import write_report

        try:
            page = write_report(self.out_dir, ground_truth=False)
        except Exception:
            log.exception("the run report could not be written")
            return None
        log.info("report: %s", page)
        return page

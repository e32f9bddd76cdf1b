"""A run's outputs, whoever ran it (one process: system.py; separate processes: the cloud's
robot sessions and its merge, cloud/): the files of each robot, ``summary.json`` (its
schema: run_summary.py) and the tables printed from it (also the HTML report's).

    <out>/<robot>/trajectory.tum   every frame (TUM; evo reads it)
    <out>/<robot>/keyframes.tum    the keyframes
    <out>/<robot>/map.ply          the robot's dense map
    <out>/<robot>/robot.json       the robot's entry of summary.json (the cloud, as it ends)
    <out>/<robot>/robot_report.json  the robot process's own report (a deployed run)
    <out>/summary.json             run_summary.RunSummary: robots, merge, config; a deployed run (the
                                   demo) adds each robot's report and the deployment; ``mcap``
                                   names run.mcap when the run wrote it
    <out>/run.mcap                 all of it as ROS 2 messages (run_mcap.py)
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np

from fleetslam.io.files import UnreadableFile, read_regular
from fleetslam.io.ply import write_ply
from fleetslam.io.trajectory import write_tum_trajectory
from fleetslam.mapping.occupancy_grid import OccupancyGrid, write_nav2_map
from fleetslam.tables import _cell, format_table

log = logging.getLogger("fleetslam.outputs")

ROBOT_SUMMARY = "robot.json"
# A robot.json is a few kB; a larger file is not one fleetslam wrote.
MAX_ROBOT_SUMMARY_BYTES = 16 << 20
ROBOT_REPORT = "robot_report.json"


def write_robot_files(robot_dir: Path, name: str, source: str, timestamps: np.ndarray,
                      poses: np.ndarray, keyframe_times: np.ndarray, keyframe_poses: np.ndarray,
                      points: np.ndarray, colors: np.ndarray,
                      online_poses: np.ndarray | None = None,
                      tracked: np.ndarray | None = None,
                      grid: OccupancyGrid | None = None) -> None:
    """A robot's trajectory, keyframes and dense map, in its own map frame; with
    ``online_poses``, the tracked frames' poses as tracking reported them frame by frame
    (what the robot heard, and published to ROS 2), before later corrections; with ``grid``,
    its nav2 map (map.pgm, map.yaml)."""
    write_tum_trajectory(robot_dir / "trajectory.tum", timestamps, poses,
                         comment=f"fleetslam robot {name} from {source}\n"
                                 "T_map_camera; map frame = first camera pose")
    if online_poses is not None:
        ok = np.ones(len(timestamps), bool) if tracked is None else np.asarray(tracked, bool)
        write_tum_trajectory(robot_dir / "online.tum", timestamps[ok], online_poses[ok],
                             comment=f"fleetslam robot {name}: each tracked frame's pose as "
                                     "tracking reported it (the feedback's), before later "
                                     "corrections\nT_map_camera")
    write_tum_trajectory(robot_dir / "keyframes.tum", keyframe_times, keyframe_poses,
                         comment=f"fleetslam robot {name} keyframes")
    write_ply(robot_dir / "map.ply", points, colors)
    if grid is not None:
        write_nav2_map(robot_dir / "map", grid, f"robot {name}'s map")


def write_robot_summary(robot_dir: Path, summary: dict[str, Any]) -> None:
    (robot_dir / ROBOT_SUMMARY).write_text(json.dumps(summary, indent=2))


def read_robot_summary(robot_dir: Path) -> dict[str, Any] | None:
    """A robot's entry as written when it ended; None if it has not (or it cannot be read:
    said, as its session's counts are then the checkpoint's)."""
    path = robot_dir / ROBOT_SUMMARY
    if not path.exists():
        return None
    try:
        entry = json.loads(read_regular(path, MAX_ROBOT_SUMMARY_BYTES,
                                        f"the limit of {MAX_ROBOT_SUMMARY_BYTES}"))
    except (UnreadableFile, UnicodeDecodeError, json.JSONDecodeError) as exc:
        log.error("%s: not a robot summary fleetslam wrote (%s); its counts are left out",
                  path, exc)
        return None
    return entry if isinstance(entry, dict) else None


def add_robot_reports(summary: dict[str, Any], out_dir: Path) -> None:
    """A deployed run: each robot's own report (``<robot>/robot_report.json``) in its entry,
    without what the file keeps for itself (the cloud's summary as the robot heard it, every
    message it sent, and each frame's CPU time)."""
    for robot in summary["robots"]:
        report = out_dir / robot["name"] / ROBOT_REPORT
        if report.exists():
            robot["robot"] = json.loads(report.read_text())
            robot["robot"].pop("cloud_summary", None)
            robot["robot"].pop("sends", None)
            robot["robot"].pop("frame_cpu_ms", None)


def add_deployment(summary: dict[str, Any], wall_s: float, endpoint: str, processes: int,
                   workers: int, offload_at: str, link: list[str]) -> None:
    """A deployed run: the cloud's merge took ``wall_time_s`` of the cloud's summary, the run
    ``wall_s`` in all; how it was deployed."""
    summary["merge_wall_time_s"] = summary["wall_time_s"]
    summary["wall_time_s"] = wall_s
    summary["deployment"] = {"endpoint": endpoint, "tls": endpoint.startswith("tls/"),
                             "processes": processes, "workers": workers,
                             "offload_at": offload_at, "link": link}


def write_summary(out_dir: Path, summary: dict[str, Any]) -> None:
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=2))


Table = tuple[list[str], list[list[Any]]]  # headers, rows (the text and the HTML report)


def camera_skipped(robot: dict[str, Any]) -> int | None:
    """Frames a robot's live camera delivered that it never took (None: a recording): from
    the cloud's summary (the robot's end message) or the robot's own report."""
    if robot.get("live_camera"):
        return robot["live_camera"]["skipped"]
    report = robot.get("robot")  # a deployed robot's report (add_robot_reports)
    if not isinstance(report, dict) or not report.get("live_source"):
        return None
    return report.get("camera_skipped")


def _cm_deg(cm: float | None, deg: float | None) -> str | None:
    """An error as "cm / deg" in one cell, 3 digits each as the tables print numbers (None:
    not scored; only cm: a summary from before rotations were scored)."""
    if cm is None:
        return None
    return _cell(cm) + ("" if deg is None else f" / {_cell(deg)}")


# The ATE's rotation is evo_ape -a -r angle_deg's: after the SE(3) Umeyama fit of positions
# (evo's -a fits rotations no better). Where the camera barely moves (fr1_rpy) that fit
# leaves the trajectory's heading loose, and the angle is large however well it tracked:
# the header says so, where the number is read, and keeps it comparable with evo's.
ATE_HEADER = "ATE RMSE cm / deg (rot. after position fit)"


def robot_table(summary: dict[str, Any]) -> Table:
    """One row per robot: frames, losses, loops, ATE and RPE (if scored: RMSE of the
    translation and of the rotation, as evo_ape -a and evo_rpe give them), speed, map size;
    with a live camera, the frames it skipped."""
    robots = summary["robots"]
    live = any(camera_skipped(r) is not None for r in robots)
    rows = []
    for r in robots:
        ate, rpe = r.get("ate") or {}, r.get("rpe") or {}
        loops = r.get("loop_closing") or {}
        rows.append([r["name"], r["frames"], *([camera_skipped(r)] if live else []),
                     r["keyframes"], r["lost_frames"],
                     loops.get("relocalisations"), loops.get("loops_accepted"),
                     _cm_deg(ate["rmse_m"] * 100 if ate else None, ate.get("rotation_rmse_deg")),
                     _cm_deg(rpe["translation_rmse_m"] * 100 if rpe else None,
                             rpe.get("rotation_rmse_deg")),
                     r.get("tracking_fps"), r["map_points"]])
    return (["robot", "frames", *(["camera skipped"] if live else []), "keyframes", "lost",
             "relocalised", "loops", ATE_HEADER, "RPE RMSE cm / deg", "fps",
             "map points"], rows)


def transport_table(summary: dict[str, Any]) -> Table | None:
    """Robot -> cloud traffic and timing of a deployed run (None in one process)."""
    deployed = [r for r in summary["robots"] if "transport" in r]
    if not deployed:
        return None
    trows = []
    for r in deployed:
        robot = r.get("robot") or {}
        counts = r["transport"]
        trows.append([
            r["name"], r["offload_at"],
            robot["frame_bytes"] / max(robot["frames"], 1) / 1000 if robot else None,
            robot.get("frames_lost_on_link"),
            sum(v for k, v in counts.items() if k.startswith("rejected")),
            robot.get("keyframe_uploads"), robot.get("upload_retries"),
            r["cloud_ms_mean"], r["latency_ms_median"], robot.get("round_trip_ms_median"),
            robot.get("round_trip_ms_p95")])
    return (["robot", "offload at", "kB/frame", "lost on link", "rejected", "KF uploads",
             "retries", "cloud ms/frame", "cloud latency ms", "round trip ms", "p95"], trows)


def _has_value(value: Any) -> bool:
    return value is not None and value != "" and value == value  # NaN != NaN


def without_empty_columns(table: Table) -> tuple[Table, list[str]]:
    """``table`` without the columns no row has a value in, and their headers (a cloud's
    merge has no ground truth, and the robots' own counts stay on the robots)."""
    headers, rows = table
    keep = [i for i in range(len(headers)) if any(_has_value(r[i]) for r in rows)] \
        if rows else list(range(len(headers)))
    dropped = [h for i, h in enumerate(headers) if i not in keep]
    return ([headers[i] for i in keep], [[r[i] for i in keep] for r in rows]), dropped


def summary_table(summary: dict[str, Any], drop_empty: bool = False) -> str:
    """The run's tables as text; ``drop_empty``: without the columns empty in every row,
    named on a line of their own."""
    dropped: list[str] = []

    def text_of(table: Table) -> str:
        if drop_empty:
            table, empty = without_empty_columns(table)
            dropped.extend(h for h in empty if h not in dropped)
        return format_table(*table)

    text = text_of(robot_table(summary))
    transport = transport_table(summary)
    if transport:
        text += "\n\nrobot -> cloud (separate processes over Zenoh)\n" + text_of(transport)
    merge = fleet_merge(summary)
    if merge:
        head, lines = merge_notes(merge)
        text += "\n\n" + "\n".join([head, text_of(merge_robot_table(merge)), *lines])
    text += f"\n\n{time_line(summary)}"
    if dropped:
        text += f"\nnot shown (no value for any robot): {', '.join(dropped)}"
    return text


def map_groups(merge: dict[str, Any] | None) -> str:
    """The merger's map groups as "r0+r1 | r2" (a cloud's status), or "none yet" before any
    robot's map reached it (a demo's first progress lines showed an empty "groups")."""
    components = (merge or {}).get("components") or {}
    return " | ".join("+".join(m) for m in components.values()) or "none yet"


def run_kind(summary: dict[str, Any]) -> str:
    """What made the summary's folder: "deployed run" (the demo: robots and a cloud in
    processes of their own), "cloud store" (a cloud's --out, written by a merge: its robots
    were tracked over the link) or "run" (``fleetslam run``, one process)."""
    if summary.get("deployment"):
        return "deployed run"
    return "cloud store" if any("offload_at" in r for r in summary.get("robots", [])) else "run"


def time_line(summary: dict[str, Any]) -> str:
    """A run's wall time, or a cloud's merge time (its summary's wall_time_s: the merge's
    own, often well under a second, which one decimal showed as 0.0 s)."""
    seconds = summary.get("wall_time_s") or 0.0
    shown = f"{seconds:.2f} s" if seconds < 10 else f"{seconds:.1f} s"
    return f"merge took {shown}" if run_kind(summary) == "cloud store" else f"wall time {shown}"


def fleet_merge(summary: dict[str, Any]) -> dict[str, Any] | None:
    """The summary's merge where robots were merged (a lone robot's run has one too, for its
    level global map, with nothing to tell about a merge)."""
    merge = summary.get("merge")
    return merge if merge and len({*(merge.get("robots") or {}),
                                   *(merge.get("not_merged") or {})}) > 1 else None


def merge_robot_table(merge: dict[str, Any]) -> Table:
    """Per robot: its group, the frames it joined at, its errors if scored."""
    evaluation = merge.get("evaluation") or {}
    relative = {r["robot"]: r for r in evaluation.get("relative_poses", [])}
    rows = []
    # Robots the merge left out before it began (not finished) have no group to show.
    left_out = {name: {"anchor": None} for name in merge.get("not_merged") or {}
                if name not in merge["robots"]}
    for name, info in sorted({**merge["robots"], **left_out}.items()):
        joined = info.get("joined")
        rel = relative.get(name, {})
        rows.append([name, info["anchor"],
                     " ".join(f"{r}:{f}" for r, f in joined["frames"].items()) if joined
                     else None,
                     rel.get("final_rotation_error_deg"),
                     None if rel.get("final_translation_error_m") is None
                     else rel["final_translation_error_m"] * 100])
    # Why a robot is not merged is said on lines of its own (merge_notes): as a column, an
    # empty one was listed among the values "not shown".
    return (["robot", "group", "joined at (robot:frame)", "rel. rot err deg",
             "rel. trans err cm"], rows)


def constraint_table(merge: dict[str, Any]) -> Table:
    """Per inter-robot constraint: the keyframes, which estimate the graph used (the dense
    refinement where accepted, else the features') and why, GNC's verdict; against ground
    truth (evaluation only) both estimates' errors where scored."""
    evaluation = merge.get("evaluation") or {}
    scored = {(c["query_robot"], c["query_frame"], c["place_robot"], c["place_frame"]): c
              for c in evaluation.get("constraints", []) if "rotation_error_deg" in c}
    rows = []
    for c in merge.get("constraints", []):
        dense = c.get("dense") or {}
        e = scored.get((c["query_robot"], c["query_frame"], c["place_robot"], c["place_frame"]),
                       {})
        # A proximity edge began as the graph's guess, not a feature estimate: none to score.
        feature_err = (None, None) if c.get("found") == "proximity" else (
            e.get("feature_rotation_error_deg", e.get("rotation_error_deg")),
            e.get("feature_translation_error_m", e.get("translation_error_m")))
        rows.append([
            f"{c['query_robot']}:{c['query_frame']}", f"{c['place_robot']}:{c['place_frame']}",
            c["inliers"], "join" if c["trusted"] else ("kept" if c["kept"] else
                                                      "rejected" if c["kept"] is False else "-"),
            c.get("used", "features") if c.get("found") != "proximity" else "dense (proximity)",
            dense.get("reason") or (None if not dense else
                                    f"moved {dense['moved_rotation_deg']:.2f} deg / "
                                    f"{dense['moved_translation_m'] * 100:.1f} cm, overlap "
                                    f"{dense['overlap']:.2f}"),
            None if feature_err[0] is None else
            f"{feature_err[0]:.2f} / {feature_err[1] * 100:.1f}",
            None if not e else f"{e['rotation_error_deg']:.2f} / "
                               f"{e['translation_error_m'] * 100:.1f}"])
    return (["query", "place", "inliers", "GNC", "edge", "dense refinement",
             "features err deg / cm (eval)", "edge err deg / cm (eval)"], rows)


def join_lines(merge: dict[str, Any]) -> list[str]:
    """Per join: the matches that made it, and how many of the pair's constraints held in
    the last optimisation."""
    lines = []
    for j in merge.get("joins", []):
        pair = set(j["robots"])
        between = [c for c in merge.get("constraints", [])
                   if {c["query_robot"], c["place_robot"]} == pair]
        lines.append(f"join {'+'.join(j['robots'])} at {j['query_robot']}:{j['query_frame']} ~ "
                     f"{j['place_robot']}:{j['place_frame']}: {j['matches']} consistent matches;"
                     f" {sum(c['kept'] is not False for c in between)} of {len(between)} "
                     f"constraints between them held "
                     f"({sum(c.get('used') == 'dense' for c in between)} dense)")
    return lines


def merge_notes(merge: dict[str, Any]) -> tuple[str, list[str]]:
    """(the groups line, the lines after the table: constraints, joint ATE)."""
    evaluation = merge.get("evaluation") or {}
    joint = evaluation.get("joint_ate")
    head = ("merge (made without ground truth; the errors are evaluation against it, "
            "afterwards): " if evaluation else "merge (no ground truth in the run): ") + \
        ", ".join("+".join(m) for m in merge["components"].values())
    scored = [c for c in evaluation.get("constraints", []) if "rotation_error_deg" in c]
    kept = [c for c in scored if c["kept"]]
    line = (f"inter-robot constraints: {len(merge['constraints'])} "
            f"({sum(c['kept'] is False for c in merge['constraints'])} rejected by GNC)")
    if kept:
        worst = max(kept, key=lambda c: c["rotation_error_deg"])
        line += (f"; kept ones against ground truth: worst {worst['rotation_error_deg']:.2f} deg"
                 f" / {max(c['translation_error_m'] for c in kept) * 100:.1f} cm")
    not_merged = merge.get("not_merged") or {}
    entered = merge.get("entered_map") or {}
    lines = [line, *join_lines(merge),
             *(["in the loaded map's frame after: " + ", ".join(
                 f"{r} {e['frames']} frames ({e['seconds']:.1f} s)"
                 for r, e in sorted(entered.items()))] if entered else []),
             *([f"not merged: {'; '.join(f'{r}: {why}' for r, why in sorted(not_merged.items()))}"]
               if not_merged else [])]
    if joint:
        lines.append(f"joint ATE of the global trajectories: {joint['rmse_m'] * 100:.2f} cm")
    return head, lines

"""The paper's Table "Performance of the whole system" for a finished deployed run: each
robot's localisation energy, the mapping energy, the system's, and the total time.

Energy is power times the time each part actually ran, as eq. 10-16 model it (P C / U is
power times compute time): the robot's stages (measured on this host, scaled to the robot's
slower CPU by U_cloud / U_local), its link while busy sending, the cloud's tracking of its
frames, and the cloud's merge for the mapping.
"""

from __future__ import annotations

from typing import Any

from fleetslam.config import PlannerConfig
from fleetslam.tables import format_table

# The paper's numbers (indoor experiment, 2 robots), beside ours.
PAPER_INDOOR = {"E_l": [221.2, 316.0], "E_localization": 537.2, "E_mapping": 3.15,
                "E_system": 540.35, "T_total_s": 291.45}
PAPER_ORIGINAL_INDOOR = {"E_system": 2482.13, "T_total_s": 1176.8}


def whole_system(summary: dict[str, Any], cfg: PlannerConfig) -> dict[str, Any]:
    """Energies (J) and time (s) of a run's summary (``fleetslam demo`` with robot reports)."""
    slower = cfg.u_cloud_gps / cfg.u_local_gps
    robots = []
    for r in summary["robots"]:
        report = r.get("robot")
        if not report:
            raise ValueError(f"robot {r['name']}: the summary has no robot report (a run "
                             f"through `fleetslam demo` has one)")
        robot_s = report["robot_compute_s"] * slower
        cloud_s = r.get("cloud_s_total") or 0.0
        e = (cfg.p_local_w * robot_s + cfg.p_tr_w * report["link_busy_s"]
             + cfg.p_cloud_w * cloud_s)
        robots.append({"robot": r["name"], "offload_at": r.get("offload_at"),
                       "robot_s": robot_s, "link_busy_s": report["link_busy_s"],
                       "cloud_s": cloud_s, "E_l": e})
    mapping_s = summary.get("merge_wall_time_s") or 0.0
    e_loc = sum(r["E_l"] for r in robots)
    e_map = cfg.p_cloud_w * mapping_s
    return {"robots": robots, "E_localization": e_loc, "E_mapping": e_map,
            "E_system": e_loc + e_map, "T_total_s": summary["wall_time_s"]}


def whole_system_table(runs: dict[str, dict[str, Any]]) -> str:
    """Side by side: each labelled run, and the paper's indoor numbers."""
    def f(x: float) -> str:  # two decimals, as the paper prints them
        return f"{x:.2f}"

    rows = []
    for label, w in runs.items():
        rows.append([label, " / ".join(f(r["E_l"]) for r in w["robots"]),
                     f(w["E_localization"]), f(w["E_mapping"]), f(w["E_system"]),
                     f(w["T_total_s"])])
    p = PAPER_INDOOR
    rows.append(["paper (indoor, partial offloading)", " / ".join(f(e) for e in p["E_l"]),
                 f(p["E_localization"]), f(p["E_mapping"]), f(p["E_system"]),
                 f(p["T_total_s"])])
    rows.append(["paper (indoor, original system)", None, None, None,
                 f(PAPER_ORIGINAL_INDOOR["E_system"]), f(PAPER_ORIGINAL_INDOOR["T_total_s"])])
    return format_table(["run", "E_l per robot J", "E_localization J", "E_mapping J",
                         "E_system J", "T_total s"], rows)

"""The paper's energy model and our time model over the candidate split points, and the
choice among them.

Energy per unit of ``frames_per_unit`` frames (paper eq. 16, with eta from eq. 31):

    E(eta) = P_local C_total eta / U_local + P_cloud C_total (1 - eta) / U_cloud + P_tr T_tr(eta)

Time per frame: the robot runs stages[:k] (slower than this host by U_cloud / U_local unless
the profile measured the robot), the link carries the point's message (and the keyframe
uploads, amortised), the cloud runs stages[k:]. A frame's latency is the sum; a stream is
pipelined (robot, link and cloud work on different frames at once), so its sustainable rate
is set by the slowest of the three, which is why the paper's "total" is less than its "sum".
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from fleetslam.config import OBJECTIVES, PlannerConfig  # OBJECTIVES: re-exported
from fleetslam.planner.profile import Profile

# The sweep of `fleetslam plan --sweep` (Mbit/s).
SWEEP_MBPS = (0.5, 1.0, 2.0, 5.0, 10.0, 20.0, 50.0, 100.0)


@dataclass
class Link:
    bandwidth_mbps: float
    latency_ms: float = 0.0

    def __post_init__(self) -> None:
        if not self.bandwidth_mbps > 0:
            raise ValueError(f"bandwidth {self.bandwidth_mbps} Mbit/s must be > 0")
        if self.latency_ms < 0:
            raise ValueError(f"latency {self.latency_ms} ms must be >= 0")


@dataclass
class Candidate:
    k: int
    eta: float
    sends: str
    bytes_per_frame: float  # frame message + keyframe uploads per frame
    t_robot_s: float  # per frame
    t_tr_s: float  # per frame, latency included
    t_cloud_s: float
    latency_s: float
    fps: float  # sustainable, pipelined
    t_tr_unit_s: float  # transmission time of frames_per_unit frames (the paper's T_tr)
    energy_j: float  # per frames_per_unit frames
    offered: bool  # the system can run at this point
    note: str = ""

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def offloading_ratios(profile: Profile) -> np.ndarray:
    """eta_k = time of stages[:k] / time of all stages (eq. 31), k = 0..n."""
    cumulative = np.concatenate([[0.0], np.cumsum(profile.stage_ms)])
    total = profile.stated_total_ms or cumulative[-1]
    return np.minimum(cumulative / total, 1.0)


def robot_stage_ms(profile: Profile, cfg: PlannerConfig) -> np.ndarray:
    scaled = np.asarray(profile.stage_ms, float) * cfg.u_cloud_gps / cfg.u_local_gps
    if profile.robot_stage_ms is None:
        return scaled
    # A stage the robot did not measure (None: beyond its front end) is scaled from the host's.
    return np.array([s if m is None else m for m, s in zip(profile.robot_stage_ms, scaled)],
                    float)


def computation_g(profile: Profile, cfg: PlannerConfig) -> float:
    """C_total: the whole pipeline's cycles per energy unit."""
    if cfg.c_total_g is not None:
        return cfg.c_total_g
    return sum(profile.stage_ms) / 1000.0 * cfg.u_cloud_gps * cfg.frames_per_unit


def energy(eta: float, t_tr_unit_s: float, c_total_g: float, cfg: PlannerConfig) -> float:
    """Paper eq. 16 for one unit of frames."""
    return (cfg.p_local_w * c_total_g * eta / cfg.u_local_gps
            + cfg.p_cloud_w * c_total_g * (1.0 - eta) / cfg.u_cloud_gps
            + cfg.p_tr_w * t_tr_unit_s)


def candidates(profile: Profile, link: Link, cfg: PlannerConfig,
               offered: tuple[int, ...] | None = None, feature_scale: float = 1.0
               ) -> list[Candidate]:
    """Every split point k = 0..n under ``link``; ``offered`` are the points the system can
    run (None: all). ``feature_scale``: the share of the profile's ORB features the robot
    keeps; from point 2 on, the message and the robot's stages scale with it (the
    per-feature parts dominate them)."""
    etas = offloading_ratios(profile)
    robot_ms = np.concatenate([[0.0], np.cumsum(robot_stage_ms(profile, cfg))])
    host_ms = np.asarray(profile.stage_ms, float)
    cloud_ms = np.array([host_ms[k:].sum() for k in range(len(host_ms) + 1)])
    c_total = computation_g(profile, cfg)
    out = []
    for k, eta in enumerate(etas):
        scale = feature_scale if k >= 2 else 1.0
        # Keyframe uploads ride on every point but total offloading (the cloud has the frame).
        uploads = profile.keyframe_bytes * profile.keyframe_fraction if k > 0 else 0.0
        per_frame = profile.frame_bytes[k] * scale + uploads
        t_send = per_frame * 8 / (link.bandwidth_mbps * 1e6)
        t_tr = t_send + link.latency_ms / 1000.0
        t_robot, t_cloud = robot_ms[k] * scale / 1000.0, cloud_ms[k] / 1000.0
        t_tr_unit = t_send * cfg.frames_per_unit
        is_offered = offered is None or k in offered
        out.append(Candidate(
            k=k, eta=float(eta), sends=profile.sends[k], bytes_per_frame=float(per_frame),
            t_robot_s=float(t_robot), t_tr_s=float(t_tr), t_cloud_s=float(t_cloud),
            latency_s=float(t_robot + t_tr + t_cloud),
            fps=float(1.0 / max(t_robot, t_send, t_cloud, 1e-9)),
            t_tr_unit_s=float(t_tr_unit), energy_j=energy(float(eta), t_tr_unit, c_total, cfg),
            offered=is_offered,
            note="" if is_offered else "not offered: the tracking map would live on both sides"))
    return out


def choose(cands: list[Candidate], cfg: PlannerConfig, objective: str | None = None
           ) -> Candidate:
    """The best offered candidate for the objective (ties: the lower k, less robot work)."""
    objective = objective or cfg.objective
    if objective not in OBJECTIVES:
        raise ValueError(f"objective {objective!r}: one of {', '.join(OBJECTIVES)}")
    pool = [c for c in cands if c.offered]
    if not pool:
        raise ValueError("no offered split point to choose from")
    if objective == "energy":
        return min(pool, key=lambda c: (c.energy_j, c.k))
    if objective == "latency":
        return min(pool, key=lambda c: (c.latency_s, c.k))
    if objective == "fps":
        return max(pool, key=lambda c: (c.fps, -c.k))
    best_e = min(c.energy_j for c in pool)
    best_l = min(c.latency_s for c in pool)
    w = cfg.mix_energy_weight
    return min(pool, key=lambda c: (w * c.energy_j / best_e + (1 - w) * c.latency_s / best_l,
                                    c.k))

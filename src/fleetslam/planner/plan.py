"""``fleetslam plan``: the candidate table at one bandwidth or a sweep, the choice, plan.json
and the paper's two figures (relative energy and transmission time against eta)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from fleetslam.config import PlannerConfig
from fleetslam.planner.model import Candidate, Link, candidates, choose
from fleetslam.planner.profile import Profile
from fleetslam.tables import format_table

def candidate_table(cands: list[Candidate], chosen: Candidate, cfg: PlannerConfig) -> str:
    unit = cfg.frames_per_unit
    rows = [[("* " if c is chosen else "  ") + str(c.k), round(c.eta, 3), c.sends,
             c.bytes_per_frame / 1000, c.t_tr_unit_s, c.energy_j, c.latency_s * 1000, c.fps,
             "" if c.offered else "not offered"] for c in cands]
    return format_table(["k", "eta", "what is sent", "kB/frame", f"T_tr s/{unit} fr",
                         f"E J/{unit} fr", "latency ms", "fps", ""], rows)


def plan(profile: Profile, links: list[Link], cfg: PlannerConfig,
         offered: tuple[int, ...] | None, objective: str | None = None) -> dict[str, Any]:
    """Candidates and the choice at every link."""
    results = []
    for link in links:
        cands = candidates(profile, link, cfg, offered)
        chosen = choose(cands, cfg, objective)
        results.append({"bandwidth_mbps": link.bandwidth_mbps, "latency_ms": link.latency_ms,
                        "chosen_k": chosen.k, "chosen_eta": chosen.eta,
                        "candidates": [c.as_dict() for c in cands]})
    return {"objective": objective or cfg.objective, "profile": profile.__dict__,
            "planner": cfg.__dict__, "links": results}


def write_plots(result: dict[str, Any], out_dir: Path) -> list[Path]:
    """E(eta) and T_tr(eta), one curve per bandwidth, the choice marked (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    unit = result["planner"]["frames_per_unit"]
    for key, label, name in (("energy_j", f"energy per {unit} frames (J)", "energy.png"),
                             ("t_tr_unit_s", f"transmission time per {unit} frames (s)",
                              "transmission_time.png")):
        fig, ax = plt.subplots(figsize=(6.4, 4.2))
        for link in result["links"]:
            cands = link["candidates"]
            etas = [c["eta"] for c in cands]
            ax.plot(etas, [c[key] for c in cands], marker="o",
                    label=f"{link['bandwidth_mbps']:g} Mbit/s")
            chosen = next(c for c in cands if c["k"] == link["chosen_k"])
            ax.plot([chosen["eta"]], [chosen[key]], marker="*", markersize=14, color="black")
        ax.set_xlabel("offloading ratio eta (share of the pipeline run on the robot)")
        ax.set_ylabel(label)
        ax.set_yscale("log")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7, ncol=2)
        ax.set_title(f"{label.split(' per')[0]} against eta (star: the choice)")
        fig.tight_layout()
        path = out_dir / name
        with matplotlib.rc_context({"axes.formatter.min_exponent": 4}):  # "20", not "2×10¹"
            fig.savefig(path, dpi=120)
        plt.close(fig)
        paths.append(path)
    return paths


def report(result: dict[str, Any], cfg: PlannerConfig) -> str:
    """The candidate table at each bandwidth (a sweep: one line per bandwidth instead)."""
    links = result["links"]
    if len(links) == 1:
        link = links[0]
        cands = [Candidate(**c) for c in link["candidates"]]
        chosen = next(c for c in cands if c.k == link["chosen_k"])
        return (f"link {link['bandwidth_mbps']:g} Mbit/s, {link['latency_ms']:g} ms; objective "
                f"{result['objective']}\n" + candidate_table(cands, chosen, cfg)
                + f"\nchoice: k = {chosen.k}, eta = {chosen.eta:.3f} ({chosen.sends})")
    rows = []
    for link in links:
        chosen = next(c for c in link["candidates"] if c["k"] == link["chosen_k"])
        rows.append([link["bandwidth_mbps"], chosen["k"], round(chosen["eta"], 3),
                     chosen["sends"], chosen["bytes_per_frame"] / 1000, chosen["energy_j"],
                     chosen["latency_s"] * 1000, chosen["fps"]])
    return (f"objective {result['objective']}\n"
            + format_table(["Mbit/s", "k", "eta", "what is sent", "kB/frame", "E J",
                            "latency ms", "fps"], rows))


def write_plan(result: dict[str, Any], out_dir: Path) -> tuple[list[Path], str]:
    """plan.json and the plots: (the files written, why the plots were not: "" if they
    were). The plots need matplotlib, of the cloud extra; the plan does not."""
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "plan.json").write_text(json.dumps(result, indent=2))
    try:
        import matplotlib  # noqa: F401
    except ImportError as exc:
        return [out_dir / "plan.json"], (f"plots not drawn: they need matplotlib "
                                         f"(pip install 'fleetslam[cloud]'; {exc})")
    return [out_dir / "plan.json", *write_plots(result, out_dir)], ""

"""The report page: one self-contained HTML file beside its PNGs (relative paths, inline CSS,
no script, nothing fetched), so it opens from disk, from a copied folder or an archive."""

from __future__ import annotations

import html
import time
from typing import Any

from fleetslam.tables import _cell
from fleetslam.reporting.plots import Figure
from fleetslam.reporting.run import RunData
from fleetslam.outputs import (constraint_table, fleet_merge, merge_notes, merge_robot_table,
                               robot_table, run_kind, time_line, transport_table)

STYLE = """
body { font: 14px/1.45 system-ui, sans-serif; margin: 2em auto; max-width: 1100px;
       padding: 0 1em; color: #222; }
h1 { font-size: 1.5em; margin-bottom: 0.2em; } h2 { font-size: 1.2em; margin-top: 1.8em; }
.meta { color: #666; } .notes { background: #fff8e0; border-left: 4px solid #e0b000;
        padding: 0.4em 1em; }
table { border-collapse: collapse; margin: 0.5em 0; font-size: 13px; }
th, td { border: 1px solid #ccc; padding: 2px 8px; } th { background: #f0f0f0; }
td.num { text-align: right; font-variant-numeric: tabular-nums; }
figure { margin: 1.2em 0; } figure img { max-width: 100%; border: 1px solid #ddd; }
figcaption { color: #555; font-size: 13px; max-width: 900px; }
"""


def _camera_note(camera: dict[str, Any] | None) -> str | None:
    """A live source's line: what it was and how many frames the robot took and skipped."""
    if camera is None:
        return None
    undelivered = camera.get("undelivered")  # None: a robot from before it was counted
    produced = "" if undelivered is None else (
        f"{camera['delivered'] + undelivered} frames produced, {undelivered} never delivered "
        f"(the camera dropped them), ")
    # The rest of the delivered: the frame waiting at the stop, those before a resume.
    rest = camera["delivered"] - camera["taken"] - camera["skipped"]
    return (f"{camera['source']}: {produced}{camera['delivered']} delivered: "
            f"{camera['taken']} taken, {camera['skipped']} skipped (the robot was busy)"
            + (f", {rest} not taken (waiting at the end, or before a resume)" if rest > 0
               else ""))


def _table(headers: list[str], rows: list[list[Any]]) -> str:
    head = "".join(f"<th>{html.escape(h)}</th>" for h in headers)
    body = "".join(
        "<tr>" + "".join(
            f'<td class="num">{html.escape(_cell(v))}</td>' if isinstance(v, int | float)
            and not isinstance(v, bool) else f"<td>{html.escape(_cell(v))}</td>" for v in row)
        + "</tr>" for row in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def _ground_truth_line(run: RunData) -> str:
    if not run.ground_truth_read:
        return ("Ground truth: not read for this report (the cloud's own report: the cloud "
                "never reads it), so the plots that need it are left out; `fleetslam report` "
                "on this folder adds them where the robots' sequences are.")
    with_gt = [r.name for r in run.robots if r.own is not None and r.own.has_gt]
    if not with_gt:
        return ("Ground truth: none for this run, so the plots that need it (error over time, "
                "aligned trajectories) are left out; every other plot is shown.")
    others = [r.name for r in run.robots if r.name not in with_gt]
    return ("Ground truth (evaluation only, read after the run from each robot's source "
            "folder or the --groundtruth file given for it; the tables' errors and the plots' "
            f"are scored from it alike): {', '.join(with_gt)}"
            + (f"; none for {', '.join(others)}" if others else "") + ".")


def render_page(run: RunData, figures: list[Figure], skipped: dict[str, str]) -> str:
    s = run.summary
    title = html.escape(f"fleetslam {run_kind(s)} {run.folder.resolve().name}")
    parts = [f"<!doctype html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
             f"<title>{title}</title><style>{STYLE}</style></head><body><h1>{title}</h1>"]
    deployment = s.get("deployment") or {}
    meta = [f"{len(run.robots)} robots", time_line(s)]
    if deployment:
        meta.append(f"{deployment.get('processes')} processes over "
                    f"{'TLS' if deployment.get('tls') else 'TCP'}, offload at "
                    f"{deployment.get('offload_at')}"
                    + (f", link {' '.join(deployment['link'])}" if deployment.get("link") else ""))
    meta.append(f"report made {time.strftime('%Y-%m-%d %H:%M:%S')}")
    parts.append(f'<p class="meta">{html.escape(" · ".join(meta))}</p>')
    notes = [_ground_truth_line(run), *run.notes]
    parts.append('<div class="notes"><ul>' + "".join(f"<li>{html.escape(n)}</li>"
                                                    for n in notes) + "</ul></div>")
    parts.append("<h2>Robots</h2>" + _table(*robot_table(s)))
    cameras = {r["name"]: r["live_camera"] for r in s.get("robots", []) if r.get("live_camera")}
    sources = [[r.name, r.source, *([_camera_note(cameras.get(r.name))] if cameras else [])]
               for r in run.robots]
    parts.append(_table(["robot", "source", *(["live camera"] if cameras else [])], sources))
    transport = transport_table(s)
    if transport:
        parts.append("<h2>Robot &rarr; cloud</h2>" + _table(*transport))
    merge = fleet_merge(s)
    if merge:
        head, lines = merge_notes(merge)
        parts.append(f"<h2>Merge</h2><p>{html.escape(head)}</p>"
                     + _table(*merge_robot_table(merge))
                     + "".join(f"<p>{html.escape(line)}</p>" for line in lines))
        if merge.get("constraints"):
            parts.append("<h3>Inter-robot constraints</h3>" + _table(*constraint_table(merge)))
    parts.append("<h2>Plots</h2>")
    for f in figures:
        parts.append(f'<figure><h3>{html.escape(f.title)}</h3>'
                     f'<img src="{html.escape(f.file)}" alt="{html.escape(f.title)}">'
                     f"<figcaption>{html.escape(f.caption)}</figcaption></figure>")
    if skipped:
        parts.append("<h2>Not shown</h2><ul>" + "".join(
            f"<li>{html.escape(k)}: {html.escape(v)}</li>" for k, v in skipped.items())
            + "</ul>")
    parts.append("</body></html>\n")
    return "\n".join(parts)

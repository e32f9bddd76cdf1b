"""The report's figures (matplotlib, Agg: no display needed). Each ``plot_*`` writes one PNG
and returns a Figure, or returns the reason it has nothing to show, so the page can say why
a figure is missing.

Views: "up" is the up direction of the cameras (-y of each camera when held level), which
holds in any frame (a map frame is a camera, ground truth may have z up or y up). Where it is
within SNAP_DEG of an axis of the frame, the views show the frame's own axes, named as evo
names them ("x (m)", "z (m)"; "-y (m)" when -y is up); otherwise the top view looks down the
cameras' up, with the trajectories' main horizontal direction across the page, and each axis
is named by its direction in the frame ("0.97x + 0.24z (m)").
"""

from __future__ import annotations

import io
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # before pyplot: files only, never a window

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.axes import Axes  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402
from PIL import Image  # noqa: E402

from fleetslam.evaluation.ate import ate_errors, rpe_errors  # noqa: E402
from fleetslam.outputs import fleet_merge  # noqa: E402

from fleetslam.reporting.run import (  # noqa: E402
    RunData,
    Trajectory,
    alignment,
    transform,
    translation_errors,
)

DPI = 110
# Log axes label 0.001 .. 9999 as plain numbers ("20", "0.5"), not "2×10¹".
PLAIN_TICKS = {"axes.formatter.min_exponent": 4}
# The map's top view is drawn as an image of at most this many cells on its long side.
MAP_CELLS = 400
# Points higher than the highest camera by this much are left out of the top view: a
# ceiling would hide the floor plan.
CEILING_MARGIN_M = 0.3
# The views use the frame's own axes when the cameras' up is this close to one of them.
SNAP_DEG = 15.0
AXIS_NAMES = "xyz"


@dataclass
class Figure:
    file: str  # name in report/
    title: str
    caption: str


Plot = Callable[[RunData, Path], "Figure | str"]


# -- geometry ----------------------------------------------------------------------------


def _up(R: np.ndarray) -> np.ndarray:
    """The up direction of cameras (N, 3, 3) held without roll, as hand-held and robot
    cameras are: every camera's x axis is then horizontal, so up is the direction
    orthogonal to all of them (their covariance's least eigenvector), which a camera
    looking down does not tilt. Cameras that barely turned leave that direction open in
    the plane across their x axis: there, the mean -y of the cameras (pitch tilts it)."""
    x = R[:, :, 0]
    mean_up = -R[:, :, 1].mean(axis=0)
    w, v = np.linalg.eigh(x.T @ x / len(x))  # ascending eigenvalues
    if w[1] > 0.02:  # x axes spread over more than about 8 degrees of heading
        up = v[:, 0] * (1.0 if v[:, 0] @ mean_up >= 0 else -1.0)
    else:
        up = mean_up - (mean_up @ v[:, 2]) * v[:, 2]
    norm = np.linalg.norm(up)
    return up / norm if norm > 1e-6 else np.array([0.0, 0.0, 1.0])


def _frame_axes(up: np.ndarray) -> np.ndarray | None:
    """Rows: the frame's two axes across ``up`` and the axis along it (signed so it points
    up, the two ordered so the top view is right-handed), or None if ``up`` is more than
    SNAP_DEG from every axis."""
    k = int(np.argmax(np.abs(up)))
    if abs(up[k]) < np.cos(np.radians(SNAP_DEG)):
        return None
    eye = np.eye(3)
    a, b = eye[(k + 1) % 3], eye[(k + 2) % 3]  # a x b = +e_k
    return np.stack([a, b, eye[k]]) if up[k] > 0 else np.stack([b, a, -eye[k]])


def axis_label(v: np.ndarray) -> str:
    """The name of a view axis (a unit vector of the frame): "x (m)", "-y (m)", or its
    components where it is no axis of the frame ("0.97x + 0.24z (m)")."""
    k = int(np.argmax(np.abs(v)))
    if abs(v[k]) > 0.9999:
        return f"{'-' if v[k] < 0 else ''}{AXIS_NAMES[k]} (m)"
    terms = [(c, n) for c, n in zip(v, AXIS_NAMES) if abs(c) >= 0.005]
    text = "".join(f"{' - ' if c < 0 else ' + '}{abs(c):.2f}{n}" for c, n in terms)
    return f"{text[3:] if text.startswith(' + ') else '-' + text[3:]} (m)"


def view_basis(poses: np.ndarray, spread: np.ndarray | None = None) -> np.ndarray:
    """Rows: horizontal axis 1, horizontal axis 2, up (the cameras' up vector): the frame's
    own axes when up is near one of them, else horizontal axis 1 along the main direction of
    ``spread`` (points (N, 3), default the camera positions)."""
    finite = poses[np.isfinite(poses).all(axis=(1, 2))]
    up = _up(finite[:, :3, :3]) if len(finite) else np.array([0.0, 0.0, 1.0])
    axes = _frame_axes(up)
    if axes is not None:
        return axes
    if spread is None:
        spread = finite[:, :3, 3] if len(finite) else np.eye(3)
    p = spread - spread.mean(axis=0)
    flat = p - np.outer(p @ up, up)  # positions projected onto the horizontal plane
    _, _, vt = np.linalg.svd(flat.T @ flat if len(flat) > 1 else np.eye(3))
    e1 = vt[0] - (vt[0] @ up) * up
    if np.linalg.norm(e1) < 1e-6:  # no horizontal spread: any horizontal axis
        e1 = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 = e1 / np.linalg.norm(e1)
    return np.stack([e1, np.cross(up, e1), up])


def _project(points: np.ndarray, basis: np.ndarray) -> np.ndarray:
    return points @ basis.T


def _save(fig: plt.Figure, path: Path, dpi: int = DPI) -> None:
    """PNG, palette-quantised when that is lossless enough: plots have few colours, and
    the page (and the README's picture) load faster."""
    buffer = io.BytesIO()
    with matplotlib.rc_context(PLAIN_TICKS):  # ticks are formatted when drawn
        fig.savefig(buffer, format="png", dpi=dpi)
    plt.close(fig)
    buffer.seek(0)
    image = Image.open(buffer).convert("RGB")
    image.quantize(256, method=Image.Quantize.MEDIANCUT).save(path, optimize=True)


Views = tuple[Axes, "Axes | None"]  # top view, side view (None: top view only)


def _legend_below(fig: plt.Figure, ax: Axes, handles: list | None = None,
                  ncol: int = 4) -> None:
    """A legend under the axes, outside them (it would hide bars or lanes), with room
    kept for it when laying out."""
    handles = handles if handles is not None else ax.get_legend_handles_labels()[0]
    rows = -(-len(handles) // ncol)
    fig.legend(handles=handles, fontsize=7, ncol=ncol, loc="lower center", frameon=False)
    fig.tight_layout(rect=(0, (0.12 + 0.2 * rows) / fig.get_figheight(), 1, 1))


def _views(axes: Views, basis: np.ndarray) -> None:
    """Axis names from the view's ``basis`` (rows: across, up the page, up)."""
    top, side = axes
    top.set_xlabel(axis_label(basis[0]))
    top.set_ylabel(axis_label(basis[1]))
    top.set_title("top view", fontsize=9)
    if side is not None:
        side.set_xlabel(axis_label(basis[0]))
        side.set_ylabel(axis_label(basis[2]))
        side.set_title("side view", fontsize=9)
    for ax in axes:
        if ax is None:
            continue
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(True, alpha=0.3)
        ax.tick_params(labelsize=7)


def _draw_path(axes: Views, positions: np.ndarray, basis: np.ndarray,
               color: str, label: str | None, dashed: bool = False) -> None:
    uvw = _project(positions, basis)
    style = {"color": color, "lw": 1.0 if dashed else 1.3, "ls": "--" if dashed else "-",
             "alpha": 0.7 if dashed else 1.0}
    top, side = axes
    top.plot(uvw[:, 0], uvw[:, 1], label=label, **style)
    if side is not None:
        side.plot(uvw[:, 0], uvw[:, 2], **style)
    if not dashed:  # where the robot started
        top.plot(uvw[:1, 0], uvw[:1, 1], "o", color=color, ms=4)
        if side is not None:
            side.plot(uvw[:1, 0], uvw[:1, 2], "o", color=color, ms=4)


# -- trajectories ------------------------------------------------------------------------


def plot_trajectories_own(run: RunData, path: Path) -> Figure | str:
    """Each robot in its own map frame, aligned to its own ground truth where it has one."""
    robots = [r for r in run.robots if r.own is not None]
    if not robots:
        return "no robot trajectory in the run folder"
    fig, grid = plt.subplots(len(robots), 2, figsize=(9, 3.4 * len(robots)), squeeze=False)
    for row, r in zip(grid, robots):
        traj = r.own
        assert traj is not None
        T = alignment([traj]) if traj.has_gt else None
        poses = traj.poses if T is None else transform(T, traj.poses)
        basis = view_basis(traj.gt if T is not None else poses)
        axes = (row[0], row[1])
        if T is not None:
            assert traj.gt is not None
            gt = traj.gt[np.isfinite(traj.gt[:, 0, 0])]
            _draw_path(axes, gt[:, :3, 3], basis, "0.45", "ground truth", dashed=True)
        _draw_path(axes, poses[:, :3, 3], basis, run.color(r.name),
                   f"{r.name} estimate" + (" (SE(3)-aligned)" if T is not None else ""))
        _views(axes, basis)
        frame = "ground-truth frame" if T is not None else \
            f"its map frame ({r.name}'s first camera), no ground truth"
        row[0].set_title(f"{r.name}: top view ({frame})", fontsize=9)
        row[0].legend(fontsize=7, loc="best")
    fig.tight_layout()
    _save(fig, path)
    return Figure(path.name, "Trajectories, each robot in its own map frame",
                  "Top and side view of every robot's trajectory.tum; where the robot's "
                  "recording has ground truth, the estimate is aligned onto it by one SE(3) "
                  "Umeyama alignment per robot (as evo_ape -a) and the ground truth is "
                  "dashed. Dot: first frame.")


def _global_frame(run: RunData) -> tuple[np.ndarray | None, list[Trajectory]]:
    """The joint alignment of the merged robots' global trajectories (None without a
    shared ground truth) and those trajectories."""
    trajs = [r.glob for r in run.merged if r.glob is not None]
    T = alignment(trajs) if run.joint_gt else None
    return T, trajs


def global_map_frame(run: RunData) -> str:
    """The name of the global map frame: the map frame of the merge's anchor robot."""
    anchor = (run.summary.get("merge") or {}).get("anchor")
    return f"global map frame = {anchor}'s first camera" if anchor else "global map frame"


def draw_global_trajectories(run: RunData, axes: Views) -> str:
    """The merged robots in the global frame on (top, side) axes; returns the frame's name."""
    T, trajs = _global_frame(run)
    posed = [t.poses if T is None else transform(T, t.poses) for t in trajs]
    if T is not None:
        gts = [t.gt[np.isfinite(t.gt[:, 0, 0])] for t in trajs if t.gt is not None]
        basis = view_basis(np.concatenate(gts))
        for g in gts:
            _draw_path(axes, g[:, :3, 3], basis, "0.45", None, dashed=True)
    else:
        basis = view_basis(np.concatenate(posed))
    for r, poses in zip(run.merged, posed):
        _draw_path(axes, poses[:, :3, 3], basis, run.color(r.name), r.name)
    _views(axes, basis)
    if T is not None:
        axes[0].plot([], [], "--", color="0.45", label="ground truth")
    axes[0].legend(fontsize=7, loc="best")
    return "ground-truth frame: one SE(3) alignment of all merged robots" if T is not None \
        else f"{global_map_frame(run)}, no ground truth"


def plot_trajectories_global(run: RunData, path: Path) -> Figure | str:
    if len(run.merged) < 2:
        return "no merged robots (global/<robot>.tum) in this run"
    fig, (top, side) = plt.subplots(1, 2, figsize=(10, 4.2))
    frame = draw_global_trajectories(run, (top, side))
    top.set_title(f"merged robots: top view\n({frame})", fontsize=9)
    fig.tight_layout()
    _save(fig, path)
    return Figure(path.name, "Trajectories in the global frame",
                  "The merged robots' global/<robot>.tum together. With ground truth they "
                  "share ONE SE(3) alignment (all robots' frames at once), so an error in "
                  "where the merge put a map shows here, and the axes are the ground "
                  "truth's: this is NOT the frame of the global map plot, which is drawn in "
                  "the global map frame (the map frame of the group's first robot). Without "
                  "ground truth, both are in the global map frame.")


# -- error over time ---------------------------------------------------------------------


def plot_errors(run: RunData, path: Path) -> Figure | str:
    own = [(r, r.own) for r in run.robots if r.own is not None and r.own.has_gt]
    if not own:
        return "no ground truth: the error over time needs it"
    T_glob, trajs = _global_frame(run)
    panels = 2 if T_glob is not None else 1
    fig, axes = plt.subplots(panels, 1, figsize=(9, 2.9 * panels), squeeze=False)
    ax = axes[0, 0]
    for r, traj in own:
        T = alignment([traj])
        if T is None:
            continue
        err = translation_errors(traj, T) * 100
        rmse = np.sqrt(np.nanmean(err**2))
        ax.plot(traj.times - traj.times[0], err, color=run.color(r.name), lw=1,
                label=f"{r.name} (RMSE {rmse:.2f} cm)")
    ax.set_title("each robot in its own map frame (SE(3)-aligned per robot)", fontsize=9)
    if T_glob is not None:
        gx = axes[1, 0]
        for r, traj in zip(run.merged, trajs):
            err = translation_errors(traj, T_glob) * 100
            rmse = np.sqrt(np.nanmean(err**2))
            gx.plot(traj.times - traj.times[0], err, color=run.color(r.name), lw=1,
                    label=f"{r.name} (RMSE {rmse:.2f} cm)")
        gx.set_title("global frame (one SE(3) alignment over the merged robots)", fontsize=9)
    for a in axes[:, 0]:
        # Robots' clocks need not share an origin (recordings), so each starts at 0.
        a.set_xlabel("time since the robot's first frame (s)")
        a.set_ylabel("translation error (cm)")
        a.grid(True, alpha=0.3)
        a.legend(fontsize=7)
        a.set_ylim(bottom=0)
    fig.tight_layout()
    _save(fig, path)
    return Figure(path.name, "Translation error over time",
                  "Per frame: distance between the aligned estimate and ground truth "
                  "(frames without ground truth are gaps).")


def plot_rotation_and_rpe(run: RunData, path: Path) -> Figure | str:
    """Per robot in its own map frame: the ATE's rotation error (evo_ape -a -r angle_deg)
    and the RPE between consecutive frames (evo_rpe, translation and angle), over time."""
    own = [(r, r.own) for r in run.robots if r.own is not None and r.own.has_gt]
    if not own:
        return "no ground truth: the rotation error and the RPE need it"
    fig, axes = plt.subplots(3, 1, figsize=(9, 7.6), sharex=True)
    panels = (("ATE rotation error (deg)", "ATE rotation: angle of (aligned estimate)^-1 "
               "ground truth, SE(3)-aligned per robot (evo_ape -a -r angle_deg)"),
              ("RPE translation (cm)", "RPE between consecutive frames (evo_rpe, delta 1 "
               "frame): translation of the relative motion's error"),
              ("RPE rotation (deg)", "RPE between consecutive frames: angle of the relative "
               "motion's error (evo_rpe -r angle_deg)"))
    for r, traj in own:
        assert traj.gt is not None
        T = alignment([traj])
        if T is None:
            continue
        t = traj.times - traj.times[0]
        _, rot = ate_errors(traj.poses, traj.gt, T)
        later, rpe_t, rpe_r = rpe_errors(traj.poses, traj.gt)
        for ax, values, times, unit in ((axes[0], rot, t, "deg"),
                                        (axes[1], rpe_t * 100, t[later], "cm"),
                                        (axes[2], rpe_r, t[later], "deg")):
            rmse = np.sqrt(np.nanmean(values**2)) if len(values) else float("nan")
            ax.plot(times, values, color=run.color(r.name), lw=1,
                    label=f"{r.name} (RMSE {rmse:.3g} {unit})")
    for ax, (ylabel, title) in zip(axes, panels):
        ax.set_ylabel(ylabel)
        ax.set_title(title, fontsize=9)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7)
        ax.set_ylim(bottom=0)
    axes[-1].set_xlabel("time since the robot's first frame (s)")
    fig.tight_layout()
    _save(fig, path)
    return Figure(path.name, "Rotation error and relative pose error over time",
                  "Each robot against its ground truth, as evo computes them: the absolute "
                  "rotation error after the robot's SE(3) alignment, and the relative pose "
                  "error of each step between consecutive frames with ground truth (drift "
                  "per frame; an alignment cancels in it), at the later frame of the step. "
                  "The alignment matches positions only: along a short or straight path it "
                  "leaves the roll about the path open, which shows as a constant rotation "
                  "error (evo's too) while the RPE stays small.")


# -- global map --------------------------------------------------------------------------


def draw_global_map(run: RunData, ax: Axes) -> None:
    """Top view of global_map.ply as an image (each cell: the colour of its highest point
    below the ceiling cut) with the robots' global paths on it."""
    assert run.map_points is not None
    trajs = [r.glob for r in run.merged if r.glob is not None]
    # Horizontal axes along the map's own main direction (a room's long wall).
    basis = view_basis(np.concatenate([t.poses for t in trajs]), run.map_points[::50])
    uvw = _project(run.map_points, basis)
    cams = np.concatenate([_project(t.poses[:, :3, 3], basis) for t in trajs])
    keep = uvw[:, 2] < cams[:, 2].max() + CEILING_MARGIN_M
    uvw = uvw[keep]
    colors = run.map_colors[keep] if run.map_colors is not None \
        else np.full((len(uvw), 3), 90, np.uint8)
    lo, hi = uvw[:, :2].min(axis=0), uvw[:, :2].max(axis=0)
    # Cells no finer than 2 cm: the map is voxel-fused at about that spacing, and finer
    # cells show its grid as speckle instead of surfaces.
    cell = max(float((hi - lo).max()) / MAP_CELLS, 0.02)
    ij = np.floor((uvw[:, :2] - lo) / cell).astype(np.int64)
    shape = (int(ij[:, 1].max()) + 1, int(ij[:, 0].max()) + 1)
    flat = ij[:, 1] * shape[1] + ij[:, 0]
    # Highest point per cell: sort by height, descending, keep each cell's first.
    order = np.argsort(-uvw[:, 2], kind="stable")
    cells, first = np.unique(flat[order], return_index=True)
    image = np.full((shape[0] * shape[1], 4), 255, np.uint8)
    image[:, 3] = 0  # empty cells transparent
    image[cells, :3] = colors[order[first]]
    image[cells, 3] = 255
    ax.imshow(image.reshape(*shape, 4), origin="lower", interpolation="nearest",
              extent=(lo[0], lo[0] + shape[1] * cell, lo[1], lo[1] + shape[0] * cell))
    for r, t in zip(run.merged, trajs):
        p = _project(t.poses[:, :3, 3], basis)
        ax.plot(p[:, 0], p[:, 1], color="white", lw=3.2, alpha=0.8)
        ax.plot(p[:, 0], p[:, 1], color=run.color(r.name), lw=1.6, label=r.name)
        ax.plot(p[:1, 0], p[:1, 1], "o", color=run.color(r.name), ms=5, mec="white")
    ax.set_aspect("equal")
    ax.set_xlabel(axis_label(basis[0]))
    ax.set_ylabel(axis_label(basis[1]))
    ax.tick_params(labelsize=7)
    ax.legend(fontsize=7, loc="best")


def plot_global_map(run: RunData, path: Path) -> Figure | str:
    if run.map_points is None or not len(run.map_points):
        return "no global_map.ply (the run made no global map)"
    if len(run.merged) < 1:
        return "no global trajectories to place the map's view"
    fig, ax = plt.subplots(figsize=(8, 6.5))
    draw_global_map(run, ax)
    x0, x1 = ax.get_xlim()
    y0, y1 = ax.get_ylim()
    fig.set_figheight(float(np.clip(7 * (y1 - y0) / max(x1 - x0, 1e-6), 3, 9)) + 1.2)
    ax.set_title(f"global map, top view, {global_map_frame(run)}\n({len(run.map_points):,} "
                 f"points; above the highest camera + {CEILING_MARGIN_M} m left out) and "
                 "global paths", fontsize=9)
    fig.tight_layout()
    _save(fig, path)
    return Figure(path.name, "Global map from above",
                  "global_map.ply seen from above (each cell shows its highest point; the "
                  "ceiling is cut off) with every merged robot's global path, both in the "
                  "fleet's level map frame (z up; the group's first robot's): no ground "
                  "truth involved, so where the trajectory plots align to ground truth their "
                  "axes differ from these.")


# -- stage times -------------------------------------------------------------------------


def plot_stage_times(run: RunData, path: Path) -> Figure | str:
    robots = [r for r in run.robots if r.stage_ms or r.robot_stage_ms]
    if not robots:
        return "the summary records no stage times"
    # Stage names in pipeline order as the summaries list them; one colour per stage.
    names: list[str] = []
    for r in robots:
        for k in [*r.robot_stage_ms, *r.stage_ms]:
            if k not in names:
                names.append(k)
    colors = {n: plt.get_cmap("tab10")(i % 10) for i, n in enumerate(names)}
    fig, ax = plt.subplots(figsize=(9, 1.2 + 0.75 * len(robots) * (2 if any(
        r.robot_stage_ms for r in robots) else 1)))
    labels, y = [], 0
    for r in robots:
        # A deployed robot's stages run on two machines; in one process there is one side.
        cloud = "cloud" if r.offload_at is not None else ""
        for side, stages in (("robot", r.robot_stage_ms), (cloud, r.stage_ms)):
            if not stages:
                continue
            widths = np.array([stages[n] for n in stages])
            lefts = np.concatenate([[0.0], np.cumsum(widths)[:-1]])
            ax.barh(y, widths, left=lefts, color=[colors[n] for n in stages],
                    hatch="//" if side == "robot" else None, edgecolor="white")
            ax.text(widths.sum(), y, f" {widths.sum():.1f} ms", va="center", fontsize=7)
            labels.append(f"{r.name} {side}".strip())
            y += 1
    ax.set_yticks(range(len(labels)), labels)
    ax.invert_yaxis()
    ax.set_xlabel("mean time per frame (ms)")
    ax.grid(True, axis="x", alpha=0.3)
    ax.set_xlim(0, ax.get_xlim()[1] * 1.1)  # room for the totals
    ax.set_title("tracking stages: mean time per frame (hatched: on the robot)", fontsize=9)
    _legend_below(fig, ax, [Line2D([], [], color=colors[n], lw=6, label=n) for n in names],
                  ncol=min(len(names), 6))
    _save(fig, path)
    return Figure(path.name, "Time per frame by stage",
                  "Mean milliseconds per frame of every tracking stage (summary.json "
                  "stage_ms; on the robot: its robot_report.json robot_stage_ms).")


# -- link --------------------------------------------------------------------------------


def plot_link(run: RunData, path: Path, bin_s: float = 1.0) -> Figure | str:
    robots = [r for r in run.robots if r.sends is not None]
    if not robots:
        return ("no per-message link record (a run in one process has no link; robot "
                "reports of a deployed run keep it in <robot>/robot_report.json)")
    fig, (bx, lx) = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    end = max(float(r.sends.end_s.max()) for r in robots if r.sends is not None)
    bins = np.arange(0.0, end + bin_s, bin_s)
    for r in robots:
        s = r.sends
        assert s is not None
        c = run.color(r.name)
        frames, kfs = ~s.keyframe, s.keyframe
        bx.plot(s.end_s[frames], s.nbytes[frames] / 1000, ".", color=c, ms=3,
                label=f"{r.name} frames ({s.nbytes[frames].mean() / 1000:.1f} kB mean)")
        if kfs.any():
            bx.plot(s.end_s[kfs], s.nbytes[kfs] / 1000, "^", color=c, ms=5, mec="black",
                    mew=0.4, label=f"{r.name} keyframe uploads ({kfs.sum()})")
        lost = ~s.delivered
        if lost.any():
            bx.plot(s.end_s[lost], s.nbytes[lost] / 1000, "x", color="red", ms=5)
        # Throughput per bin from each message's bytes at the time its last bit left.
        mbit, _ = np.histogram(s.end_s, bins, weights=s.nbytes * 8 / 1e6)
        lx.step(bins[:-1], mbit / bin_s, where="post", color=c, label=r.name)
    if any((~r.sends.delivered).any() for r in robots if r.sends is not None):
        bx.plot([], [], "x", color="red", label="lost on the link")
    if run.bandwidth_mbps:
        lx.axhline(run.bandwidth_mbps, color="black", ls="--", lw=1,
                   label=f"link {run.bandwidth_mbps:g} Mbit/s")
    bx.set_yscale("log")
    bx.set_ylabel("message size (kB)")
    bx.set_title("bytes of every frame and keyframe upload", fontsize=9)
    lx.set_ylabel(f"sent (Mbit/s, {bin_s:g} s bins)")
    lx.set_xlabel("time since the robot's first frame (s)")
    lx.set_title("link use over time", fontsize=9)
    for a in (bx, lx):
        a.grid(True, alpha=0.3)
        a.legend(fontsize=7, loc="best")
    fig.tight_layout()
    _save(fig, path)
    return Figure(path.name, "Bytes per frame and link use",
                  "From each robot's robot_report.json (sends): every message it put on "
                  "its (emulated) link, at the time its last bit was sent.")


# -- merge events ------------------------------------------------------------------------


def plot_merge(run: RunData, path: Path) -> Figure | str:
    merge = fleet_merge(run.summary)
    if not merge:
        return "one robot: no merge"
    names = sorted(merge.get("robots") or {r.name for r in run.robots})
    lane = {n: i for i, n in enumerate(names)}
    frames = {r.name: r.frames for r in run.robots}
    fig, ax = plt.subplots(figsize=(9, 1.6 + 0.9 * len(names)))
    for n in names:
        ax.plot([0, max(frames.get(n, 1) - 1, 0)], [lane[n]] * 2, color=run.color(n)
                if n in frames else "0.5", lw=6, alpha=0.35, solid_capstyle="butt")
    styles = {"kept": ("tab:green", "-", "kept"), "rejected": ("tab:red", ":", "rejected by GNC"),
              "open": ("0.5", "--", "not (yet) in a graph")}
    seen = set()
    for c in merge.get("constraints", []):
        q, p = c["query_robot"], c["place_robot"]
        if q not in lane or p not in lane:
            continue
        kind = "kept" if c.get("kept") else "rejected" if c.get("kept") is False else "open"
        color, ls, label = styles[kind]
        ax.plot([c["query_frame"], c["place_frame"]], [lane[q], lane[p]], color=color, ls=ls,
                lw=1.0, alpha=0.8, label=None if kind in seen else label)
        seen.add(kind)
    for e in merge.get("joins", []):
        q, p = e.get("query_robot"), e.get("place_robot")
        if q not in lane or p not in lane:
            continue
        ax.plot([e["query_frame"]], [lane[q]], "*", color="gold", mec="black", ms=15, zorder=5)
        ax.plot([e["place_frame"]], [lane[p]], "*", color="gold", mec="black", ms=15, zorder=5)
        ax.annotate(f"{' + '.join(e['robots'])} joined ({e['matches']} matches)",
                    (e["query_frame"], lane[q]), xytext=(6, 10), textcoords="offset points",
                    fontsize=8)
    ax.plot([], [], "*", color="gold", mec="black", ms=10, label="join (the robots' frames)")
    ax.set_yticks(range(len(names)), names)
    ax.set_ylim(-0.6, len(names) - 0.4)
    ax.invert_yaxis()
    ax.set_xlabel("frame index of each robot")
    ax.grid(True, axis="x", alpha=0.3)
    ax.set_title("merge events: inter-robot constraints (a line joins the two frames that saw "
                 "the same place) and joins", fontsize=9)
    _legend_below(fig, ax)
    _save(fig, path)
    return Figure(path.name, "Merge events",
                  "Each robot is a lane along its frames; every inter-robot constraint links "
                  "the query robot's frame to the frame of the other robot it recognised, "
                  "coloured by what the global pose graph (GNC) made of it; stars mark the "
                  "constraint that joined two groups.")


# -- overview (the README's picture) -----------------------------------------------------


def plot_overview(run: RunData, path: Path) -> Figure | str:
    """Global trajectories (top view) beside the global map from above; a run without a
    merge shows its robots' own trajectories instead."""
    if len(run.merged) >= 2 and run.map_points is not None:
        fig, (tx, mx) = plt.subplots(1, 2, figsize=(10, 4.3),
                                     gridspec_kw={"width_ratios": [1, 1.15]})
        frame = draw_global_trajectories(run, (tx, None))
        tx.set_title(f"merged trajectories, top view\n({frame})", fontsize=9)
        draw_global_map(run, mx)
        mx.set_title(f"global map from above with the robots' paths\n({global_map_frame(run)})",
                     fontsize=9)
    else:
        robots = [r for r in run.robots if r.own is not None]
        if not robots:
            return "nothing to show"
        fig, tx = plt.subplots(figsize=(6, 4.3))
        # One view for all: each robot's map frame is its first camera, alike if the
        # cameras are mounted alike.
        basis = view_basis(np.concatenate([r.own.poses for r in robots if r.own is not None]))
        for r in robots:
            assert r.own is not None
            _draw_path((tx, None), r.own.poses[:, :3, 3], basis, run.color(r.name),
                       f"{r.name} (own map frame)")
        _views((tx, None), basis)
        tx.legend(fontsize=7)
        tx.set_title("trajectories, top view", fontsize=9)
    fig.suptitle(f"fleetslam run {run.folder.resolve().name}", fontsize=10)
    fig.tight_layout()
    _save(fig, path, dpi=90)
    return Figure(path.name, "Overview", "The run at a glance.")


PLOTS: list[tuple[str, Plot]] = [
    ("overview.png", plot_overview),
    ("trajectories_global.png", plot_trajectories_global),
    ("trajectories_own.png", plot_trajectories_own),
    ("error_over_time.png", plot_errors),
    ("rotation_rpe_over_time.png", plot_rotation_and_rpe),
    ("global_map.png", plot_global_map),
    ("stage_times.png", plot_stage_times),
    ("link.png", plot_link),
    ("merge_events.png", plot_merge),
]

"""An experiment for the merger's place check (issue 46's "more joins", issue 44's entry):
does checking a robot's keyframe against a map keyframe *with its neighbours* pass where
the one-pair check (merging/inter_robot.py) does not, and is it right when it passes?

For each keyframe of ``--robot``, against each keyframe of ``--map-robot`` of a saved map
(one a run wrote after loading a map, so both robots are in it): the query's descriptors are
matched to the map keyframe's own first, then to each neighbour's within ``--width``
keyframes (each on its own: a union of overlapping keyframes fails Lowe's ratio on the
landmarks they share), the neighbours' points moved into the map keyframe's camera by the
map's poses; then the merger's RANSAC and reprojection refinement, unchanged. Printed: the
best pair's refined inliers (merge.min_refined_inliers passes), and that pair's error against
ground truth (evaluation only, read after; 7-Scenes frame indices, the robot's offset by
``--offset``). ``--width 0`` is the merger's check against every keyframe.

    .venv/bin/python bench/place_check_neighbours.py runs/tuesday/map --robot r0-2 \\
        --map-robot r0 --offset 400 --width 1
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "src"))

from fleetslam.config import Config  # noqa: E402
from fleetslam.io.trajectory import read_tum_trajectory  # noqa: E402
from fleetslam.merging import inter_robot as ir  # noqa: E402
from fleetslam.merging.saved_map import SavedRobot, read_map  # noqa: E402
from fleetslam.registration.metrics import transform_error  # noqa: E402
from fleetslam.tables import format_table  # noqa: E402
from fleetslam.transforms import invert  # noqa: E402

GROUND_TRUTH = ROOT.parent / "shared" / "data" / "7scenes_redkitchen_seq01_f0000-0599" / \
    "groundtruth.txt"


def neighbourhood(robot: SavedRobot, i: int, width: int
                  ) -> list[tuple[np.ndarray, np.ndarray]]:
    """(descriptors, points in keyframe i's camera) of keyframe i, then of its neighbours."""
    out = []
    order = [i] + [j for j in range(max(0, i - width), min(len(robot.keyframes), i + width + 1))
                   if j != i]
    for j in order:
        f = robot.keyframes[j].features
        idx = ir._depth_backed(f)
        points = robot.camera.backproject(f.uv[idx], f.depth[idx].astype(np.float64))
        T = invert(robot.poses[i]) @ robot.poses[j]
        out.append((f.descriptors[idx], points @ T[:3, :3].T + T[:3, 3]))
    return out


def check(query: SavedRobot, k: int, place: list[tuple[np.ndarray, np.ndarray]],
          config: Config) -> tuple[int, np.ndarray | None]:
    """Refined inliers of query keyframe k against a neighbourhood, and the pose found."""
    lc, tc = config.loop_closing, config.tracking
    qf = query.keyframes[k].features
    qi = ir._depth_backed(qf)
    taken = np.zeros(len(qi), bool)
    points = np.zeros((len(qi), 3))
    for descriptors, P in place:
        ids = ir.descriptor_match(qf.descriptors[qi], descriptors, np.arange(len(descriptors)),
                                  tc.max_hamming, tc.match_ratio)
        new = (ids >= 0) & ~taken
        taken |= new
        points[new] = P[ids[new]]
    kp, dst = qi[taken], points[taken]
    if len(kp) < lc.min_ransac_inliers:
        return 0, None
    depth = qf.depth[kp].astype(np.float64)
    src = query.camera.backproject(qf.uv[kp], depth)
    threshold = np.maximum(lc.ransac_inlier_m, lc.ransac_inlier_depth_ratio * depth)
    rigid = ir.ransac_rigid(src, dst, threshold, lc.ransac_iterations, lc.min_ransac_inliers,
                            np.random.default_rng(config.merge.seed + k))
    if rigid is None:
        return 0, None
    T, good = ir.optimize_pose(query.camera, rigid.T_target_source, dst, qf.uv[kp], depth,
                               config.orb.scale_factor ** qf.keypoints[kp, 5],
                               tc.virtual_baseline_m)
    return int(good.sum()), T


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("map", type=Path)
    parser.add_argument("--robot", required=True, help="the robot whose keyframes are checked")
    parser.add_argument("--map-robot", required=True, help="the robot they are checked against")
    parser.add_argument("--width", type=int, default=1, help="neighbours each side (0: none)")
    parser.add_argument("--offset", type=int, default=0,
                        help="the robot's first frame in the recording (for ground truth)")
    args = parser.parse_args()
    config = Config()
    saved = read_map(args.map)
    query, place = saved.robots[args.robot], saved.robots[args.map_robot]
    _, gt = read_tum_trajectory(GROUND_TRUTH)
    places = [neighbourhood(place, i, args.width) for i in range(len(place.keyframes))]
    rows = []
    for k, q in enumerate(query.keyframes):
        best: tuple[int, int, np.ndarray | None] = (0, -1, None)
        for i, neighbours in enumerate(places):
            n, T = check(query, k, neighbours, config)
            if n > best[0]:
                best = (n, i, T)
        n, i, T = best
        err = None if T is None else transform_error(
            T, invert(gt[place.keyframes[i].frame_index]) @ gt[args.offset + q.frame_index])
        rows.append([q.frame_index, n, "-" if i < 0 else place.keyframes[i].frame_index,
                     "-" if err is None else f"{err.rotation_deg:.1f}/{err.translation_m * 100:.1f}",
                     "yes" if n >= config.merge.min_refined_inliers else "no"])
    print(format_table(["frame", "refined inliers", "best place frame", "error deg/cm",
                        "passes"], rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Is the colour camera the camera the system assumes? On 7-Scenes (colour not registered to
depth; the shipped intrinsics are the depth camera's, fx = fy = 585), fit the colour camera's
focal length and its rotation against the depth camera from feature matches, and see what
the fit does to rotations and to tracking (issue 46, lever 3).

    .venv/bin/python bench/colour_registration.py [--out bench/results/colour_registration.json]
                                                 [--no-tracking]

Frame pairs 10 frames apart, every 12 frames. Per pair: ORB matches between the two colour
images; each match's depth looked up where the colour ray meets the depth image; the model
(colour focal f, principal point as shipped, no rotation between the cameras: a 1.5 deg one
moved the median error by 0.01 px, so these residuals cannot tell it) scored by the
reprojection of the first frame's points into the second colour image through a reference
relative pose. Two references: ground truth (KinectFusion, evaluation only) and depth alone
(small_gicp GICP of the two depth clouds from identity, no ground truth): if the second
fit lands where the first does, a robot can find its own colour camera. For the shipped
and the fitted focal: the median reprojection error, the per-axis scale of PnP rotations
against ground truth, and the tracker's ATE over the 600 frames (fleetslam's own pipeline
with the colour camera given and ``depth_intrinsics`` the shipped ones).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import small_gicp
from scipy.spatial.transform import Rotation

from shared_data import SEVEN_SCENES

from fleetslam.config import load_config
from fleetslam.datasets.tum import RgbdSequence, detect_camera
from fleetslam.evaluation.fleet import run_ate
from fleetslam.system import track_robot
from fleetslam.tables import format_table

GAP, EVERY = 10, 12


def _depth(folder: Path, i: int, camera) -> np.ndarray:
    raw = cv2.imread(str(folder / f"frame-{i:06d}.depth.png"), cv2.IMREAD_UNCHANGED)
    return camera.depth_to_metres(raw).astype(np.float64)


def _depth_cloud(depth: np.ndarray, f: float, c: tuple[float, float]) -> np.ndarray:
    v, u = np.mgrid[0:depth.shape[0]:2, 0:depth.shape[1]:2]
    z = depth[v, u]
    ok = (z > 0.2) & (z < 4.0)
    return np.stack([(u[ok] - c[0]) / f * z[ok], (v[ok] - c[1]) / f * z[ok], z[ok]], 1)


def collect(folder: Path):
    camera, _ = detect_camera(folder)
    gt = RgbdSequence(folder).gt_poses
    orb, matcher = cv2.ORB_create(1500), cv2.BFMatcher(cv2.NORM_HAMMING)
    pairs = []
    for a in range(0, len(gt) - GAP, EVERY):
        b = a + GAP
        grey = [cv2.imread(str(folder / f"frame-{i:06d}.color.jpg"), cv2.IMREAD_GRAYSCALE)
                for i in (a, b)]
        (ka, da), (kb, db) = (orb.detectAndCompute(g, None) for g in grey)
        good = [m for m, n in matcher.knnMatch(da, db, k=2) if m.distance < 0.7 * n.distance]
        pa = np.array([ka[m.queryIdx].pt for m in good])
        pb = np.array([kb[m.trainIdx].pt for m in good])
        depth = _depth(folder, a, camera)
        clouds = [_depth_cloud(_depth(folder, i, camera), camera.fx, (camera.cx, camera.cy))
                  for i in (b, a)]
        dense = small_gicp.align(clouds[0], clouds[1], registration_type="GICP",
                                 downsampling_resolution=0.02, max_correspondence_distance=0.2)
        pairs.append({"a": a, "b": b, "pa": pa, "pb": pb, "depth": depth,
                      "gt": np.linalg.inv(gt[b]) @ gt[a],  # frame a's camera into b's
                      "depth_only": np.asarray(dense.T_target_source)})
    return camera, pairs


def colour_camera(camera, f: float):
    """The colour camera of focal ``f`` whose depth image is the shipped (depth) camera's."""
    return replace(camera, fx=f, fy=f,
                   depth_intrinsics=(camera.fx, camera.fy, camera.cx, camera.cy))


def first_frame_points(colour, p: dict) -> tuple[np.ndarray, np.ndarray]:
    """The matches' points in frame a's camera (N x 3) and their depths (0: none), each
    depth read where the colour ray meets the depth image (Camera.depth_pixels)."""
    at = np.rint(colour.depth_pixels(p["pa"], p["pa"])).astype(int)
    h, w = p["depth"].shape
    inside = (at[:, 0] >= 0) & (at[:, 0] < w) & (at[:, 1] >= 0) & (at[:, 1] < h)
    z = np.zeros(len(at))
    z[inside] = p["depth"][at[inside, 1], at[inside, 0]]
    return colour.backproject(p["pa"], z), z


def residuals(f: float, camera, pairs, reference: str) -> np.ndarray:
    """Per match: how far frame a's point lands from its match in colour image b (pixels),
    the colour camera's focal length ``f`` (its principal point the shipped one), through
    the ``reference`` relative pose; 0 where a point has no depth."""
    out = []
    colour = colour_camera(camera, f)
    for p in pairs:
        T = p[reference]
        X, z = first_frame_points(colour, p)
        X = X @ T[:3, :3].T + T[:3, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            r = np.hypot(f * X[:, 0] / X[:, 2] + camera.cx - p["pb"][:, 0],
                         f * X[:, 1] / X[:, 2] + camera.cy - p["pb"][:, 1])
        r[(z <= 0) | ~np.isfinite(r)] = 0.0
        out.append(r)
    return np.concatenate(out)


def median_px(f: float, camera, pairs, reference: str) -> float:
    e = residuals(f, camera, pairs, reference)
    return float(np.median(e[e > 0]))


def fit(camera, pairs, reference: str) -> float:
    """The focal length (2 px steps, 460-640) with the smallest median reprojection error."""
    return float(min(np.arange(460.0, 641.0, 2.0),
                     key=lambda f: median_px(f, camera, pairs, reference)))


def pnp_rotation_scale(f: float, camera, pairs) -> list[float]:
    """Per axis (x, y, z), PnP rotations against ground truth: sum(est * true) / sum(true^2)."""
    est, true = [], []
    K = np.array([[f, 0, camera.cx], [0, f, camera.cy], [0, 0, 1.0]])
    colour = colour_camera(camera, f)
    for p in pairs:
        X, z = first_frame_points(colour, p)
        ok = z > 0
        found, rvec, _, _ = cv2.solvePnPRansac(X[ok], p["pb"][ok], K, None,
                                               reprojectionError=3.0, iterationsCount=200)
        if found:
            est.append(rvec.ravel())
            true.append(Rotation.from_matrix(p["gt"][:3, :3]).as_rotvec())
    E, T = np.array(est), np.array(true)
    return [float((E[:, k] * T[:, k]).sum() / (T[:, k] ** 2).sum()) for k in range(3)]


def tracking_ate_cm(folder: Path, camera, f: float) -> float:
    colour = camera if f == camera.fx else colour_camera(camera, f)
    run = track_robot("rk", str(folder), RgbdSequence(folder, camera=colour), load_config(None),
                      show_progress=False)
    return run_ate(run)["rmse_m"] * 100


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="bench/results/colour_registration.json")
    parser.add_argument("--no-tracking", action="store_true", help="skip the two tracking runs")
    args = parser.parse_args()
    if not SEVEN_SCENES.exists():
        raise SystemExit(f"needs {SEVEN_SCENES}")
    camera, pairs = collect(SEVEN_SCENES)
    rows, results = [], []
    for label, f, reference in (("shipped", camera.fx, "gt"),
                                ("fitted to ground truth", fit(camera, pairs, "gt"), "gt"),
                                ("fitted to depth alone", fit(camera, pairs, "depth_only"),
                                 "depth_only")):
        error = median_px(f, camera, pairs, "gt")
        scale = pnp_rotation_scale(f, camera, pairs)
        ate = None if args.no_tracking or label == "fitted to depth alone" \
            else tracking_ate_cm(SEVEN_SCENES, camera, f)
        results.append({"model": label, "reference": reference, "focal": f,
                        "reprojection_median_px_against_gt": error,
                        "pnp_rotation_scale_xyz": scale, "tracking_ate_cm": ate})
        rows.append([label, f, error, " ".join(f"{x:.3f}" for x in scale), ate])
    print(format_table(["colour model", "focal px", "reproj. px (gt)",
                        "PnP rotation scale x y z", "tracking ATE cm"], rows))
    print(f"{len(pairs)} frame pairs {GAP} frames apart; cores: {os.cpu_count()}")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"date": time.strftime("%Y-%m-%d %H:%M"), "pairs": len(pairs),
                               "results": results}, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()

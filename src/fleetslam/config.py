"""The one configuration object of fleetslam. Every default is named here, once, beside
what the setting may be (validation/rules.py: ``Annotated[int, at_least(1)]``).

Load from TOML with :func:`load_config`; unknown keys are an error so typos do not pass
silently, and a value of the wrong type or out of its range names its key and file. A
loaded config is frozen: a variant (a command-line flag's, a test's) is a new config from
:meth:`Config.with_values`, checked as a file's values are.
"""

from __future__ import annotations

import dataclasses
import re
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

from fleetslam.validation.endpoints import endpoint_problem, host_problem, http_endpoint_problem
from fleetslam.validation.names import name_problem
from fleetslam.validation.rules import (ANY_TEXT, FINITE, FRACTION, Bound, OneOf, Text, above,
                                        at_least, between, checked, rules_of)

# The choices of string settings, also what the wire and the planner accept.
IMAGE_CODECS = ("png", "jpeg")
OBJECTIVES = ("energy", "latency", "fps", "mix")

ENDPOINT = Text(endpoint_problem, "a Zenoh endpoint PROTOCOL/ADDRESS, e.g. tcp/HOST:PORT")
HOST = Text(host_problem, "a host name or an IP address")
# The coordination service of many workers; empty: none.
ETCD_ENDPOINT = Text(lambda s: http_endpoint_problem(s) if s else None,
                     "empty, or an etcd endpoint https://HOST:PORT (http://HOST:PORT for "
                     "an etcd without TLS)")
# A worker id is a Zenoh key chunk (transport/keys.py); empty: chosen by the worker.
WORKER_ID = Text(lambda s: name_problem(s) if s else None,
                 "empty, or 1..64 characters of A-Z a-z 0-9 _ -")
# rerun's memory limit syntax: a size with a unit, or a share of the RAM.
MEMORY_SIZE = Text(lambda s: None if re.fullmatch(r"\d+(\.\d+)?\s*([KMGT]i?B|B|%)", s)
                   else "must be a size such as 1GiB, 512MB or 25%",
                   "a size such as 1GiB, 512MB or 25%")


# Algorithm parameters: what tracking, mapping, loop closing, merging and the planner
# compute from the frames (the paper's and ORB-SLAM's parameters among them).


@dataclass(frozen=True)
class OrbConfig:
    """ORB extraction (paper: OpenCV ORB, as in ORB-SLAM)."""

    # Upper bounds: OpenCV takes these as C ints (ORB_create gets 2 x n_features).
    n_features: Annotated[int, between(1, 1_000_000)] = 1000
    n_levels: Annotated[int, between(1, 32)] = 8
    scale_factor: Annotated[float, above(1.0)] = 1.2
    fast_threshold: Annotated[int, between(1, 255)] = 20
    # Cells of the grid the features are spread over, so texture-rich corners do not
    # take the whole budget (ORB-SLAM does the same with its quadtree).
    grid_cols: Annotated[int, between(1, 1000)] = 8
    grid_rows: Annotated[int, between(1, 1000)] = 6


@dataclass(frozen=True)
class TrackingConfig:
    """Matching, PnP and keyframe decision."""

    min_depth_m: Annotated[float, at_least(0.0)] = 0.1
    max_depth_m: Annotated[float, above(0.0)] = 7.0
    # Hamming distance (bits of 256) above which a descriptor match is not trusted.
    max_hamming: Annotated[int, between(0, 256)] = 64
    # Lowe ratio between best and second-best match.
    match_ratio: Annotated[float, Bound(0.0, 1.0, lo_open=True)] = 0.85
    # Reprojection error (pixels) for PnP RANSAC inliers and for refinement.
    ransac_reproj_px: Annotated[float, above(0.0)] = 3.0
    ransac_iterations: Annotated[int, between(1, 1_000_000)] = 200
    ransac_confidence: Annotated[float, Bound(0.0, 1.0, lo_open=True, hi_open=True)] = 0.999
    # Fewer PnP inliers than this is a tracking loss.
    min_inliers: Annotated[int, at_least(4)] = 20
    # Pose from the motion model's prediction first (ORB-SLAM's TrackWithMotionModel:
    # motion-only BA on the guided matches, no RANSAC), kept when at least this fraction of
    # the matches are inliers; otherwise, and when 0, PnP RANSAC on the matches.
    prediction_min_inlier_ratio: Annotated[float, FRACTION] = 0.7
    # Keyframe when inliers drop below this fraction of the first frame tracked after the
    # newest keyframe ...
    keyframe_inlier_ratio: Annotated[float, FRACTION] = 0.55
    # ... or when the camera moved this far from the reference keyframe.
    keyframe_translation_m: Annotated[float, at_least(0.0)] = 0.15
    keyframe_rotation_deg: Annotated[float, between(0.0, 180.0)] = 12.0
    # Landmarks from this many recent keyframes form the local map matched against when
    # the prediction fails.
    local_map_keyframes: Annotated[int, at_least(1)] = 6
    # Which landmarks guided matching and fusion search: "covisible" is ORB-SLAM's local map
    # (the newest keyframe, the keyframes sharing landmarks with it, and the recent ones), so
    # a return to an old place is found by the loop closer, which spreads the drift along
    # the loop; "all" matches every landmark in view (the old place snaps the pose, and the
    # drift stays where it was).
    local_map_scope: Annotated[str, OneOf(("all", "covisible"))] = "all"
    # Covisible keyframes of the newest keyframe in the local map (most shared first).
    local_map_covisible: Annotated[int, at_least(0)] = 20
    # Search radius (pixels, at octave 0) around a landmark's predicted position ...
    guided_radius_px: Annotated[float, above(0.0)] = 25.0
    # ... searched first within this smaller radius (0: off), the wide one only when it
    # finds fewer than min_guided_matches (ORB-SLAM's motion-model search, widened when it
    # fails): in a densely mapped room the candidates grow with the radius squared.
    guided_narrow_radius_px: Annotated[float, at_least(0.0)] = 12.0
    # Fewer guided matches than this: match against the whole local map instead.
    min_guided_matches: Annotated[int, at_least(0)] = 60
    # Virtual stereo baseline for the depth residual (ORB-SLAM's RGB-D "bf" / fx).
    virtual_baseline_m: Annotated[float, above(0.0)] = 0.08
    # After this many lost frames in a row, restart the map at the predicted pose.
    lost_frames_before_reset: Annotated[int, at_least(1)] = 15
    # A repeated image (byte-identical, as 7-Scenes fills dropped frames) is detected by
    # this fraction of keypoints at the same place with the same descriptor.
    repeated_frame_fraction: Annotated[float, Bound(0.0, 1.0, lo_open=True)] = 0.98
    # Landmarks projected with a pose already found (relocalisation, loop verification) are
    # searched within this radius in pixels at octave 0 (ORB-SLAM RGB-D: th 3 x 2.5 px).
    local_map_radius_px: Annotated[float, above(0.0)] = 7.5
    # Also take a keyframe as ORB-SLAM's RGB-D tracking does (using the observation records):
    # inliers below a fraction of the reference keyframe's established landmarks, or too few
    # close points tracked while many are untracked.
    orb_slam_keyframe_policy: bool = True
    # ORB-SLAM thRefRatio for stereo / RGB-D.
    keyframe_reference_ratio: Annotated[float, FRACTION] = 0.75
    # While the local mapper is busy (a local BA still in a worker), ORB-SLAM's reference
    # test makes a keyframe only when tracking is weak: inliers below this fraction of the
    # reference (ORB-SLAM's c1c, 0.25); without it a densely mapped place made a keyframe at
    # nearly every frame. In-line (one process) the mapper is never busy.
    keyframe_wait_for_mapper: bool = True
    keyframe_weak_ratio: Annotated[float, FRACTION] = 0.25
    # "Close" points: depth below this many virtual baselines (ORB-SLAM ThDepth, TUM: 40).
    close_depth_baselines: Annotated[float, above(0.0)] = 40.0
    # Keyframe when fewer close points than this are tracked (ORB-SLAM: 100) ...
    keyframe_close_tracked: Annotated[int, at_least(0)] = 100
    # ... and more close points than this are not (ORB-SLAM: 70).
    keyframe_close_untracked: Annotated[int, at_least(0)] = 70
    # Local bundle adjustment of keyframe poses and landmarks at every keyframe (ORB-SLAM's
    # local mapping; where it runs: ``local_mapping``).
    local_ba: bool = True
    # Keyframes optimised: the new one and its most covisible ones (ORB-SLAM: all covisible).
    local_ba_window: Annotated[int, at_least(1)] = 10
    # Landmarks two keyframes must share to be covisible (ORB-SLAM's covisibility edge: 15).
    covisibility_min_shared: Annotated[int, at_least(1)] = 15
    # Levenberg-Marquardt iterations: robust pass, then inlier-only pass (ORB-SLAM: 5, 10).
    local_ba_iterations: Annotated[tuple[int, int], at_least(1)] = (5, 10)
    # ... each pass ending early once an iteration lowers the error by less than this
    # fraction (gtsam's default: 1e-5; docs/decisions.md).
    local_ba_relative_tolerance: Annotated[float, above(0.0)] = 1e-3
    # Where a cloud runs local BA: "async" in worker processes, its result written into
    # the map at a later frame, so a keyframe does not hold up the frames behind it
    # (ORB-SLAM's LocalMapping thread); "inline" at the keyframe, deterministic (the
    # exactness tests). One-process runs and robots tracking at point 6 are always inline.
    local_mapping: Annotated[str, OneOf(("async", "inline"))] = "async"
    # Worker processes of a cloud for local BA, shared by its robots' sessions ...
    local_mapping_workers: Annotated[int, at_least(1)] = 1
    # ... at this niceness (Linux nice, 0-19): when the cores are short, a robot's next
    # frame goes before a keyframe's local BA, whose requests then supersede each other
    # (ORB-SLAM's local mapper aborting its BA for new keyframes).
    local_mapping_nice: Annotated[int, between(0, 19)] = 10
    # ... and how long a solve may take before it is dropped (the map stays as it was).
    local_ba_timeout_s: Annotated[float, above(0.0)] = 30.0
    # Where tracking needs a worker's answer now (local BA before a loop correction, the
    # last local BA and loop query at a robot's end), it waits this long, then does the
    # work itself: a niced worker is starved by the busy tracking that waits for it.
    worker_wait_s: Annotated[float, at_least(0.0)] = 1.0
    # Cull new landmarks as ORB-SLAM does (MapPointCulling) during their first keyframes.
    cull_landmarks: bool = True
    # ... when matched in fewer than this fraction of the frames predicted to see them ...
    cull_min_found_ratio: Annotated[float, FRACTION] = 0.25
    # ... or, two keyframes after creation, observation weight (with depth 2, without 1)
    # still below this (ORB-SLAM RGB-D: more than 3) ...
    cull_min_observation_weight: Annotated[int, at_least(0)] = 4
    # ... checked for this many keyframes after creation (ORB-SLAM: 3).
    cull_probation_keyframes: Annotated[int, at_least(0)] = 3
    # At a keyframe, search unmatched keypoints against the landmarks projected into it
    # (ORB-SLAM's fuse) so a view of a known landmark adds an observation, not a duplicate.
    fuse_at_keyframe: bool = True
    # Fuse search radius in pixels at octave 0, scaled by the octave (ORB-SLAM Fuse: 3).
    fuse_radius_px: Annotated[float, above(0.0)] = 3.0
    # Fuse descriptor distance bound (ORB-SLAM's TH_LOW: 50).
    fuse_max_hamming: Annotated[int, between(0, 256)] = 50
    # Cull redundant keyframes as ORB-SLAM does (KeyFrameCulling): at a keyframe, each of its
    # covisible keyframes whose close landmarks are nearly all seen by enough others at the
    # same or a finer scale gives up its observations (its pose and place-recognition entry
    # stay), so a place revisited pass after pass keeps about one pass's keyframes.
    cull_keyframes: bool = True
    # ... redundant: more than this fraction of its close landmarks (ORB-SLAM: 0.9) ...
    keyframe_redundant_fraction: Annotated[float, FRACTION] = 0.9
    # ... are each observed by at least this many other keyframes (ORB-SLAM: 3).
    keyframe_redundant_observers: Annotated[int, at_least(1)] = 3


@dataclass(frozen=True)
class PlaceRecognitionConfig:
    """Keyframe database: binary nearest-neighbour voting over ORB descriptors, or a bag
    of words on a trained vocabulary."""

    # "nearest_neighbour": exact Hamming neighbours (faiss) with idf-weighted votes, no
    # vocabulary (better recall); "bag_of_words": DBoW2-style L1 score on ``vocabulary``
    # (faster queries on large maps: the exact index grows with the map).
    method: Annotated[str, OneOf(("nearest_neighbour", "bag_of_words"))] = "nearest_neighbour"
    # A vocabulary file written by `fleetslam vocabulary` (bag_of_words only).
    vocabulary: Annotated[str, ANY_TEXT] = ""
    # Tree of a vocabulary `fleetslam vocabulary` trains: children per node, depth.
    vocabulary_branching: Annotated[int, at_least(2)] = 10
    vocabulary_levels: Annotated[int, at_least(1)] = 4

    # Neighbours looked up per query descriptor (a landmark seen by several old keyframes
    # votes for each of them).
    neighbours: Annotated[int, at_least(1)] = 8
    # A neighbour farther than this (bits of 256) casts no vote (ORB-SLAM's TH_LOW).
    max_hamming: Annotated[int, between(0, 256)] = 50
    # Candidates returned per query, best score first ...
    top_k: Annotated[int, at_least(1)] = 3
    # ... each scoring at least this fraction of the best one.
    min_score_ratio: Annotated[float, FRACTION] = 0.75


@dataclass(frozen=True)
class LoopClosingConfig:
    """Loop detection (place recognition), geometric verification and correction."""

    enabled: bool = True
    # No loop is searched before the map has this many keyframes ...
    min_keyframes: Annotated[int, at_least(0)] = 10
    # ... nor against keyframes fewer than this many keyframes older than the query, or
    # sharing at least ``covisibility_min_shared`` landmarks with it (tracking already
    # ties those to the query).
    min_keyframe_gap: Annotated[int, at_least(0)] = 10
    # A candidate's place: the candidate and this many of its most covisible keyframes,
    # whose landmarks are matched against the query keyframe.
    candidate_neighbours: Annotated[int, at_least(0)] = 5
    # Geometric verification: 3D-3D RANSAC on depth-backed matches, then a motion-only
    # refinement with every landmark of the place projected into the query.
    ransac_iterations: Annotated[int, between(1, 1_000_000)] = 300
    # A 3D match is an inlier within max(inlier_m, inlier_depth_ratio * depth).
    ransac_inlier_m: Annotated[float, above(0.0)] = 0.03
    ransac_inlier_depth_ratio: Annotated[float, at_least(0.0)] = 0.02
    min_ransac_inliers: Annotated[int, at_least(3)] = 30
    # Inliers of the refined pose (reprojection with depth, chi-square test).
    min_refined_inliers: Annotated[int, at_least(1)] = 60
    # Detections on consecutive keyframes whose loop corrections agree within these bounds
    # are required before a loop is closed (a single match can be a look-alike).
    consistent_detections: Annotated[int, at_least(1)] = 2
    consistency_rotation_deg: Annotated[float, between(0.0, 180.0)] = 3.0
    consistency_translation_m: Annotated[float, at_least(0.0)] = 0.10
    # A detection stays usable for consistency for this many keyframes.
    consistency_window_keyframes: Annotated[int, at_least(1)] = 3
    # Pose graph (gtsam, graduated non-convexity with a truncated least squares loss on
    # loop edges; odometry and covisibility edges are known inliers). Standard deviations
    # of a keyframe-to-keyframe relative pose:
    edge_sigma_rotation_deg: Annotated[float, above(0.0)] = 0.3
    edge_sigma_translation_m: Annotated[float, above(0.0)] = 0.005
    # Covisibility edges join keyframes sharing at least this many landmarks (ORB-SLAM's
    # essential graph: 100).
    pose_graph_min_shared: Annotated[int, at_least(1)] = 100
    # After a loop is corrected, bundle-adjust the whole map (every keyframe and landmark).
    global_ba: bool = True
    global_ba_iterations: Annotated[tuple[int, int], at_least(1)] = (5, 10)
    seed: Annotated[int, at_least(0)] = 0
    # With asynchronous local mapping (a cloud), the database query of each keyframe runs in
    # the local mapping worker (faiss holds the GIL); verification and correction stay on
    # the tracking thread. False: the query runs there too, as in-line.
    query_in_worker: bool = True
    # The worker keeps each session's keyframe database and is sent only the keyframes
    # added since its last query; it keeps at most this many (the least recently queried
    # goes first: a session that ended without saying so; one that comes back is sent its
    # database whole).
    worker_databases: Annotated[int, at_least(1)] = 16


@dataclass(frozen=True)
class RelocalisationConfig:
    """Finding the pose against the robot's own keyframes after tracking is lost."""

    enabled: bool = True
    # Candidate keyframes tried per lost frame (place recognition order).
    candidates: Annotated[int, at_least(1)] = 3
    min_inliers: Annotated[int, at_least(4)] = 40


@dataclass(frozen=True)
class MapConfig:
    """Per-robot dense map from keyframes."""

    voxel_m: Annotated[float, above(0.0)] = 0.02
    max_depth_m: Annotated[float, above(0.0)] = 4.0
    # Back-project every n-th pixel: a keyframe at full density is ~300k points.
    pixel_stride: Annotated[int, at_least(1)] = 2


@dataclass(frozen=True)
class FsHicpConfig:
    """FS-HICP as the paper's section IV.B specifies it (our reading: shared/paper-notes.md
    section 2, outside this repository)."""

    max_depth_m: Annotated[float, above(0.0)] = 7.0
    coarse_voxel_m: Annotated[float, above(0.0)] = 0.1
    coarse_max_corr_m: Annotated[float, above(0.0)] = 0.2
    # Coarse level runs while the fitness score is >= this fraction of the initial score.
    coarse_score_fraction: Annotated[float, FRACTION] = 0.5
    fine_voxel_m: Annotated[float, above(0.0)] = 0.05
    fine_max_corr_m: Annotated[float, above(0.0)] = 0.1
    fine_corr_shrink_m: Annotated[float, at_least(0.0)] = 0.001
    # Internal ICP iterations per Align call.
    align_iterations: Annotated[int, at_least(1)] = 2
    # Simulated annealing: accept a non-improving step with this probability.
    accept_worse_probability: Annotated[float, FRACTION] = 0.3
    # Stop after this many non-improving steps in a row.
    max_no_improve: Annotated[int, at_least(1)] = 3
    # Convergence precision on the fitness score change (m^2).
    score_epsilon: Annotated[float, at_least(0.0)] = 1e-7
    # Fitness score used to steer the levels, with r = the level's starting max
    # correspondence distance (0.2 m coarse, 0.1 m fine):
    #   "pcl": PCL's default getFitnessScore, mean d^2 over all points (the paper's call);
    #          on partial overlap it is dominated by points with no counterpart.
    #   "inliers": mean d^2 over points with d <= r; it rewards sliding off until only a
    #          small, well-fitting patch still overlaps (seen on planar overlaps).
    #   "truncated": mean of min(d^2, r^2); a lost neighbour costs r^2, a far one no more.
    fitness: Annotated[str, OneOf(("pcl", "inliers", "truncated"))] = "truncated"
    # Hard caps so a pathological pair cannot run forever.
    max_coarse_steps: Annotated[int, at_least(1)] = 200
    max_fine_steps: Annotated[int, at_least(1)] = 400
    seed: Annotated[int, at_least(0)] = 0
    num_threads: Annotated[int, at_least(1)] = 2


@dataclass(frozen=True)
class MergeConfig:
    """Joining robots into one global map: inter-robot place recognition, consistency, the
    global pose graph, FS-HICP refinement and the global outputs."""

    enabled: bool = True
    # Place-recognition candidates verified per other robot and new keyframe.
    candidates: Annotated[int, at_least(1)] = 3
    # Each robot's keyframes as the merger searches them (nearest_neighbour place
    # recognition): "exact" (every stored descriptor, as the loop closer) or "approximate":
    # exact up to place_index_exact_up_to keyframes, then a graph index grown with each
    # keyframe (backend/place_recognition.py), whose query stays about flat as maps grow.
    place_index: Annotated[str, OneOf(("exact", "approximate"))] = "approximate"
    place_index_exact_up_to: Annotated[int, at_least(0)] = 100
    # The graph index: neighbours per node, and the breadth of each search.
    place_index_links: Annotated[int, between(4, 64)] = 16
    place_index_breadth: Annotated[int, between(8, 1024)] = 64
    # The cloud's merger searches places in a process of its own at this niceness (0-19):
    # the search then takes neither the GIL nor a core from the robots tracking in the same
    # worker (merging/place_search.py); off: on the merger's thread. A process that answers
    # nothing for search_timeout_s while a search waits, and used no CPU meanwhile (hung,
    # not starved: waited for up to 5 timeouts while it works), turns the search in-line
    # for good.
    # Nothing but the merger's own queue waits for it (status and merges do not:
    # cloud/merge/merger_service.py).
    search_process: bool = True
    search_nice: Annotated[int, between(0, 19)] = 10
    search_timeout_s: Annotated[float, above(0.0)] = 60.0
    # The cloud's merger solves its pose graphs in a process of its own at this niceness
    # (merging/graph_solver.py): gtsam holds the GIL while it solves, and a fleet's graph
    # held a worker's robots and its lease's beat for seconds. A solve not answered within
    # solve_timeout_s is solved in-line (and the next in a fresh process); off: in-line.
    solve_process: bool = True
    solve_nice: Annotated[int, between(0, 19)] = 10
    solve_timeout_s: Annotated[float, above(0.0)] = 300.0
    # A keyframe that waited longer than this for the cloud's merger is indexed at once and
    # its search put off until nothing newer waits (counted): an overloaded merger keeps up
    # with the robots first (local BA's latest-only rule, for the merger).
    search_behind_s: Annotated[float, above(0.0)] = 5.0
    # A candidate is verified like a loop (loop_closing's RANSAC settings, keyframe to
    # keyframe); matches left after the reprojection refinement of the query pose:
    min_refined_inliers: Annotated[int, at_least(1)] = 50
    # Matches (from different keyframes) that must imply the same map-to-map transform,
    # within loop_closing's consistency bounds, before two robots join.
    consistent_detections: Annotated[int, at_least(1)] = 2
    # Global pose graph: each robot's own keyframe-to-keyframe edges, and the inter-robot
    # edges (a single keyframe pair's alignment is looser than tracking's).
    odometry_sigma_rotation_deg: Annotated[float, above(0.0)] = 0.3
    odometry_sigma_translation_m: Annotated[float, above(0.0)] = 0.005
    inter_sigma_rotation_deg: Annotated[float, above(0.0)] = 1.0
    inter_sigma_translation_m: Annotated[float, above(0.0)] = 0.02
    # Dense refinement of each inter-robot constraint (merging/dense_constraint.py): GICP
    # of the two keyframes' depth clouds, started from the feature estimate. Kept when it
    # converges on enough overlapping points without moving beyond the bounds below (a
    # wrong start is refused, not "refined"); its Hessian, scaled so the stiffest
    # translation direction has dense_sigma_translation_m, is fused with the feature edge.
    dense_refine: bool = True
    dense_voxel_m: Annotated[float, above(0.0)] = 0.02
    dense_neighbours: Annotated[int, between(5, 100)] = 10
    dense_max_correspondence_m: Annotated[float, above(0.0)] = 0.10
    dense_max_iterations: Annotated[int, between(1, 1000)] = 30
    dense_min_points: Annotated[int, at_least(10)] = 500
    dense_min_overlap: Annotated[float, FRACTION] = 0.3
    dense_max_rotation_deg: Annotated[float, above(0.0)] = 5.0
    dense_max_translation_m: Annotated[float, above(0.0)] = 0.15
    dense_sigma_translation_m: Annotated[float, above(0.0)] = 0.002
    # Joined robots' keyframes the graph puts near each other (camera centres within
    # proximity_distance_m, optical axes within proximity_angle_deg) are registered on
    # their depth from where the graph puts them, wherever the robots overlap, not only
    # where features matched: each keyframe with the nearest keyframe of another robot of
    # its group, kept by the dense_* bounds above and judged by GNC.
    proximity_constraints: bool = True
    proximity_distance_m: Annotated[float, above(0.0)] = 0.5
    proximity_angle_deg: Annotated[float, above(0.0)] = 30.0
    # FS-HICP refines each joined robot's dense map against the rest of its group.
    fshicp_refine: bool = True
    # The global OctoMap (.bt): leaf size, and how far rays from a keyframe are cast.
    octomap_resolution_m: Annotated[float, above(0.0)] = 0.05
    octomap_max_range_m: Annotated[float, above(0.0)] = 4.0
    seed: Annotated[int, at_least(0)] = 7
    # Each joined robot is told where its map lies in its group's frame (cloud/
    # fleet_frames.py) after a join or a new inter-robot constraint, at most every
    # placement_every_s, when it moved by more than these; every robot's latest again
    # every placement_resend_s.
    placement_every_s: Annotated[float, above(0.0)] = 1.0
    placement_move_m: Annotated[float, at_least(0.0)] = 0.005
    placement_move_deg: Annotated[float, at_least(0.0)] = 0.2
    placement_resend_s: Annotated[float, above(0.0)] = 10.0


@dataclass(frozen=True)
class GridConfig:
    """The 2D occupancy grid every map also writes for nav2's map_server
    (mapping/occupancy_grid.py): ``global_map.pgm`` / ``.yaml`` and each robot's."""

    resolution_m: Annotated[float, above(0.0)] = 0.05
    # Obstacles: map points this high above the floor (the robot's height band).
    min_height_m: Annotated[float, at_least(0.0)] = 0.1
    max_height_m: Annotated[float, above(0.0)] = 1.5
    # Up in the map frame (the robot's first camera: x right, y down, z forward) where the
    # map shows no floor; a level camera's up is 0 -1 0 (not all zero).
    up: Annotated[tuple[float, float, float], FINITE] = (0.0, -1.0, 0.0)
    # The floor: a plane among the lowest points, its normal within this of the cameras'
    # up, at least this many points within floor_inlier_m of it.
    floor_max_tilt_deg: Annotated[float, between(0.0, 90.0)] = 30.0
    floor_inlier_m: Annotated[float, above(0.0)] = 0.03
    floor_min_points: Annotated[int, at_least(3)] = 200
    # A cell is occupied with this many map points in the band (one can be noise).
    occupied_min_points: Annotated[int, at_least(1)] = 2
    # Depth rays count as free space this far from their camera (the depth sensor's range).
    max_range_m: Annotated[float, above(0.0)] = 4.0
    # Unknown cells around what was seen.
    margin_cells: Annotated[int, at_least(0)] = 5


@dataclass(frozen=True)
class PlannerConfig:
    """The offloading planner: the paper's energy model (eq. 10-16, 31; its Table "Parameter
    values" as defaults), the time model and the objective."""

    # Power (W) of the robot's CPU, the cloud's CPU and the robot's radio while sending.
    p_local_w: Annotated[float, at_least(0.0)] = 0.9
    p_cloud_w: Annotated[float, at_least(0.0)] = 0.3
    p_tr_w: Annotated[float, at_least(0.0)] = 1.3
    # CPU speeds (G cycles/s); their ratio is how much slower the robot runs a stage than
    # this host (the cloud) unless a profile measured the robot itself.
    u_local_gps: Annotated[float, above(0.0)] = 1.2
    u_cloud_gps: Annotated[float, above(0.0)] = 3.3
    # Computation of the whole pipeline per energy unit (G cycles); None: from the measured
    # stage times (host seconds x u_cloud_gps x frames_per_unit).
    c_total_g: Annotated[float | None, above(0.0)] = None
    # The paper tabulates energy and transmission time per 10 frames.
    frames_per_unit: Annotated[int, at_least(1)] = 10
    # "energy", "latency", "fps" (highest sustainable frame rate) or "mix" (weighted sum of
    # energy and latency, each relative to its best candidate).
    objective: Annotated[str, OneOf(OBJECTIVES)] = "energy"
    mix_energy_weight: Annotated[float, FRACTION] = 0.5
    # The link when nothing measured one: bandwidth (Mbit/s) and one-way latency (ms).
    bandwidth_mbps: Annotated[float, above(0.0)] = 10.0
    latency_ms: Annotated[float, at_least(0.0)] = 0.0
    # Frames measured for a profile.
    profile_frames: Annotated[int, at_least(1)] = 60
    # Online (a robot with --offload-at auto): re-plan every this many frames, among the
    # points the cloud can switch between frame by frame, lowering the ORB features or
    # sending every n-th frame only when no point keeps up with the camera (target_fps).
    replan_frames: Annotated[int, at_least(1)] = 30
    online_points: Annotated[tuple[int, ...], between(0, 3)] = (0, 1, 2, 3)
    feature_options: Annotated[tuple[int, ...], at_least(1)] = (1000, 700, 500)
    frame_step_options: Annotated[tuple[int, ...], at_least(1)] = (1, 2)
    target_fps: Annotated[float, above(0.0)] = 30.0
    # A new setting must promise this much more throughput to replace the current one.
    switch_gain: Annotated[float, at_least(1.0)] = 1.15
    # The link estimate looks back over the last this many sends, at most this many seconds
    # (a count, so that it follows a link that got faster within a few frames).
    link_window_sends: Annotated[int, at_least(1)] = 20
    link_window_s: Annotated[float, above(0.0)] = 3.0


# Deployment settings: where frames come from, how robot and cloud talk, how the cloud's
# workers share robots, what a run shows and writes.


@dataclass(frozen=True)
class SourceConfig:
    """Where a robot's frames come from besides a sequence folder (datasets/): ROS bags,
    ROS 2 topics, live cameras."""

    # Colour and depth images are paired when their stamps are at most this far apart
    # (TUM's associate.py: 20 ms); unpaired images are counted.
    pair_tolerance_s: Annotated[float, at_least(0.0)] = 0.02
    # Topics of a bag or of live ROS 2; empty: found when the bag has one of each.
    rgb_topic: Annotated[str, ANY_TEXT] = ""
    depth_topic: Annotated[str, ANY_TEXT] = ""
    camera_info_topic: Annotated[str, ANY_TEXT] = ""
    # A live camera that delivers no frame this long ends the robot's session as a stop
    # does (end, uploads, map), the reason in its report.
    live_frame_timeout_s: Annotated[float, above(0.0)] = 10.0
    # Live ROS 2 topics over rmw_zenoh (datasets/ros2_topics.py, source spec `ros2` or
    # `ros2:ENDPOINT`). The robot's ROS 2 Zenoh router: rmw_zenoh's default, on the robot
    # (fleetslam's own endpoint, transport.endpoint, is on another port).
    ros_endpoint: Annotated[str, ENDPOINT] = "tcp/localhost:7447"
    # ROS_DOMAIN_ID of the camera's nodes; -1: the ROS_DOMAIN_ID environment variable, as
    # ROS 2 reads it (0 without it).
    ros_domain_id: Annotated[int, between(-1, 232)] = -1
    # A Zenoh config file (JSON5) for the session to the ROS 2 router (TLS, ...); empty: a
    # client of ros_endpoint, no multicast. Not transport.zenoh_config: that is the cloud's.
    ros_zenoh_config: Annotated[str, ANY_TEXT] = ""
    # Topic discovery waits until the live publishers have not changed this long, so a
    # camera node still declaring its topics is not judged half-way.
    ros_discovery_settle_s: Annotated[float, at_least(0.0)] = 0.5
    # Messages a live image topic keeps waiting for its partner (colour or depth).
    ros_waiting_messages: Annotated[int, at_least(1)] = 4


@dataclass(frozen=True)
class SyntheticConfig:
    """The built-in synthetic multi-robot scene."""

    seed: Annotated[int, at_least(0)] = 1
    n_robots: Annotated[int, at_least(1)] = 2
    frames_per_robot: Annotated[int, at_least(1)] = 120
    width: Annotated[int, at_least(1)] = 640
    height: Annotated[int, at_least(1)] = 480
    fx: Annotated[float, above(0.0)] = 525.0
    fy: Annotated[float, above(0.0)] = 525.0
    cx: Annotated[float, FINITE] = 319.5
    cy: Annotated[float, FINITE] = 239.5
    fps: Annotated[float, above(0.0)] = 30.0
    room_size_m: Annotated[tuple[float, float, float], above(0.0)] = (6.0, 5.0, 2.8)
    n_furniture: Annotated[int, at_least(0)] = 8
    # Kinect-like depth noise: sigma(z) = a + b * (z - 0.4)^2 (Nguyen et al. 2012).
    depth_noise_a: Annotated[float, at_least(0.0)] = 0.0012
    depth_noise_b: Annotated[float, at_least(0.0)] = 0.0019
    depth_dropout: Annotated[float, FRACTION] = 0.02
    max_depth_m: Annotated[float, above(0.0)] = 5.0


@dataclass(frozen=True)
class CameraConfig:
    """The camera on the robot, beyond what its images and calibration say."""

    # The camera's mounting (REP 105): its optical frame (x right, y down, z forward) in
    # the robot's base_link (x forward, z up) as x y z qx qy qz qw, the order of ROS's
    # static_transform_publisher. Unset: not known. Given, the fleet's map frame is the
    # anchor robot's base_link at its first frame (mapping/map_frame.py).
    base_link: Annotated[tuple[float, float, float, float, float, float, float] | None,
                         FINITE] = None


@dataclass(frozen=True)
class WireConfig:
    """The binary message between robot and cloud (wire/)."""

    # zstd over each message payload (descriptors barely shrink; keypoints and images do).
    compress: bool = True
    zstd_level: Annotated[int, between(1, 22)] = 3
    # Images inside frame messages (split points 0 and 1): "png" is lossless, so the cloud's
    # poses equal the in-memory run; "jpeg" is smaller but changes what the cloud sees.
    frame_image_codec: Annotated[str, OneOf(IMAGE_CODECS)] = "png"
    jpeg_quality: Annotated[int, between(1, 100)] = 90
    # Keyframe uploads for the dense map: colour only feeds the map's point colours.
    keyframe_rgb_codec: Annotated[str, OneOf(IMAGE_CODECS)] = "jpeg"
    # Inter-frame coding (wire/inter.py): a robot codes each descriptor against the nearest
    # one of frames the cloud acknowledged (points 2-5), lossless, about 40 % fewer bytes.
    # Off: every frame is coded alone.
    inter_frame: bool = True
    # An intra frame (coded alone) at least every this many frames: rare, as recovery does
    # not need them (a frame whose reference the cloud lacks is refused, intra ones follow).
    intra_every: Annotated[int, at_least(1)] = 300
    # Acknowledged frames a message is coded against (the newest ones), at most 8.
    inter_references: Annotated[int, between(1, 8)] = 8
    # A descriptor's reference is searched among keypoints at most this many pyramid levels
    # from its own (the same corner mostly lands on its own level; wider costs the robot
    # time for about the same bytes). The robot's choice: nothing of it is sent.
    inter_octaves: Annotated[int, at_least(0)] = 0
    # Decoded frames the cloud keeps per robot as references (0: it refuses inter frames),
    # ~33 kB each: a busy cloud's feedback comes tens of frames late.
    reference_frames: Annotated[int, at_least(0)] = 64


@dataclass(frozen=True)
class LinkConfig:
    """Emulated robot-to-cloud link on the robot's send path (0 = not limited)."""

    bandwidth_mbps: Annotated[float, at_least(0.0)] = 0.0
    latency_ms: Annotated[float, at_least(0.0)] = 0.0
    # Probability that a frame message is lost (keyframe uploads are retried until acked).
    loss: Annotated[float, between(0.0, 1.0, hi_open=True)] = 0.0
    seed: Annotated[int, at_least(0)] = 0


@dataclass(frozen=True)
class TransportConfig:
    """Zenoh endpoints and the reliability of keyframe uploads and the robot's handshake."""

    # Not Zenoh's own 7447: ROS 2's router (rmw_zenohd) listens there on a robot computer.
    endpoint: Annotated[str, ENDPOINT] = "tcp/127.0.0.1:7450"
    # A Zenoh config file (JSON5) every fleetslam process starts from: a lab's TLS,
    # authentication, access control and routers. Empty: peer mode, no multicast.
    zenoh_config: Annotated[str, ANY_TEXT] = ""
    # Wait this long for a keyframe upload's acknowledgement before sending it again ...
    ack_timeout_s: Annotated[float, above(0.0)] = 2.0
    # ... and give up (an error, never a silent loss) after this many attempts.
    max_attempts: Annotated[int, at_least(1)] = 30
    # A robot waits this long for the cloud to answer its hello before retrying.
    connect_timeout_s: Annotated[float, above(0.0)] = 2.0
    # How long a robot or a cloud worker waits for anything to answer at the endpoint (it
    # may start before its cloud: it says so at once, then keeps trying).
    reach_deadline_s: Annotated[float, at_least(0.0)] = 600.0
    # A router (the lone cloud, `fleetslam router`) that has waited this long to hand a
    # message to one receiver whose queue is full (an unreachable worker or robot) drops
    # that receiver's link; it reconnects by itself. The wait holds one of the router's
    # threads, and a few such waits stop every robot's messages.
    router_block_s: Annotated[float, between(0.1, 60.0)] = 1.0
    # How long `fleetslam status` and `merge` wait for the cloud's first answer, reaching
    # its endpoint included (their --deadline), before saying what to check ...
    ask_deadline_s: Annotated[float, above(0.0)] = 20.0
    # ... and how long a merge may then take (tens of seconds on large maps).
    merge_timeout_s: Annotated[float, above(0.0)] = 600.0
    # A robot or operator whose open session hears nothing from the cloud this long says
    # what to check (no cloud there, or its access control dropping our messages, which
    # Zenoh does not report), and keeps waiting.
    silence_hint_s: Annotated[float, above(0.0)] = 3.0
    # The cloud's bounds: robots it serves at once, and frames waiting per robot (the
    # oldest is dropped beyond it: frames are best effort, keyframes are not).
    max_sessions: Annotated[int, at_least(1)] = 64
    max_queued_frames: Annotated[int, at_least(1)] = 256
    # Bytes a session may hold for its robot (frames waiting, undecoded and decoded, uploads
    # waiting, reference frames); beyond it frames and uploads are dropped unread and the
    # robot told to slow down (cloud/session/memory_budget.py). Twice what an honest robot's
    # window of frames in flight, uploads and references hold.
    session_budget_mb: Annotated[float, above(0.0)] = 64.0
    # Bytes all sessions may hold: each session reserves its budget, so the cloud opens at
    # most cloud_budget_mb // session_budget_mb sessions. A reservation, not a shared pool:
    # one robot's flood can never take the room another robot's session needs.
    cloud_budget_mb: Annotated[float, above(0.0)] = 4096.0
    # An unfinished session that hears nothing from its robot this long is checkpointed and
    # closed (its threads and memory freed); the robot's next message restores it.
    idle_session_s: Annotated[float, above(0.0)] = 900.0
    # ... and one that never tracked a frame (nothing to checkpoint) after this long (a full
    # cloud gives such a session's slot to the next hello at once, if no frame came).
    idle_empty_session_s: Annotated[float, above(0.0)] = 30.0
    # A robot refused because the cloud is full says hello again this many times, waiting
    # full_retry_s, then twice that, and so on (sessions free up: robots end, empty ones
    # expire), then stops saying the cloud is full. Any other refusal stops it at once.
    full_retries: Annotated[int, at_least(0)] = 3
    full_retry_s: Annotated[float, at_least(0.0)] = 5.0
    # A robot rejected more often than this (a broken or hostile client) has its frames and
    # uploads dropped unread for a while, so its flood cannot starve the other sessions.
    max_rejections_per_s: Annotated[float, above(0.0)] = 50.0
    misbehaving_pause_s: Annotated[float, at_least(0.0)] = 2.0
    # Control messages (hello, end) a robot may send a second; a genuine robot sends one
    # every connect_timeout_s at most. Beyond it they are rejected (and count towards the
    # pause above): each costs the session work and a reply.
    max_control_per_s: Annotated[float, above(0.0)] = 20.0
    # Keyframe uploads the cloud stores per robot (about 0.2 MB each at the map's stride).
    max_keyframes: Annotated[int, at_least(1)] = 20_000
    # A session checkpoint larger than this (with all the chunks it names) is refused
    # unread, and no more than this is ever read of one (nothing in it is decompressed:
    # cloud/session/store.py); room for a session at max_keyframes.
    max_checkpoint_bytes: Annotated[int, at_least(1 << 20)] = 4 << 30
    # A keyframe's checkpoint is captured at most this often per session: one asked sooner
    # waits, and the capture at the end of the interval covers every keyframe since (each
    # still acknowledged and handed to the merger only once on disk), as each costs the
    # worker's GIL; 0: one per keyframe. A crash loses no acknowledged keyframe either way.
    checkpoint_interval_s: Annotated[float, at_least(0.0)] = 1.0
    # Frames tracked since the last checkpoint are checkpointed at least this often, so a
    # restarted cloud resumes a robot near where it was even when it made no keyframe for
    # long (a robot in a place already mapped); 0: only at keyframes and at the end.
    checkpoint_every_s: Annotated[float, at_least(0.0)] = 30.0
    # When a robot says it ended, frames it sent before may still be on their way (they
    # travel on another key): the cloud waits this long for them, then takes them as lost.
    end_grace_s: Annotated[float, at_least(0.0)] = 2.0
    # Frames a robot keeps (RGB-D) for keyframe uploads the cloud may still ask for.
    keyframe_buffer_frames: Annotated[int, at_least(1)] = 120
    # Frames a robot has sent without their feedback yet, at most (flow control, 0: no
    # bound): a robot faster than its cloud session waits instead of overflowing the
    # session's queue (gaps in the trajectory); 12 is 0.4 s at 30 fps, a WAN round trip.
    max_frames_in_flight: Annotated[int, at_least(0)] = 12
    # ... waiting at most this long per frame (a cloud that stopped answering must not
    # stop the robot: its hello and resends take over).
    in_flight_wait_s: Annotated[float, above(0.0)] = 5.0


@dataclass(frozen=True)
class PlacementConfig:
    """Cloud workers sharing robots (cloud/coordination/placement.py): how bids for a robot are
    settled, and the leases of their coordination service (cloud/coordination/ownership.py)."""

    # A worker's name in the liveliness tokens; empty: w-<host>-<pid>.
    worker_id: Annotated[str, WORKER_ID] = ""
    # Bids are compared this long after a worker bids (longer than the routers' round
    # trip, so every worker sees the same bids). With etcd: a worker ranked after another
    # for a new robot takes it once this long per worker before it passed with no grant.
    settle_s: Annotated[float, above(0.0)] = 0.3
    # A liveliness query of the routers gives up after this long.
    query_timeout_s: Annotated[float, above(0.0)] = 2.0
    # Bidding rounds for one robot before the worker leaves it to the robot's next message.
    max_rounds: Annotated[int, at_least(1)] = 5
    # Each worker measures the cores it keeps busy (its process and its local-mapping
    # processes, averaged over load_window_s) and tells the others this often; a new robot
    # goes to the worker with the least (cloud/coordination/worker_load.py).
    load_report_s: Annotated[float, above(0.0)] = 0.5
    load_window_s: Annotated[float, above(0.0)] = 5.0
    # A robot heard from within this many seconds is at work: its worker's load counts it.
    active_s: Annotated[float, above(0.0)] = 2.0
    # What a robot counts until its cost is measured (cores): one granted since its worker's
    # last load report, or at work beyond the robots its worker's load average has taken in
    # (it came within load_window_s).
    robot_cost_cores: Annotated[float, above(0.0)] = 0.4
    # Many workers with a coordination service: the etcd (http://HOST:PORT) that decides which
    # worker owns which robot and the merger, with fencing (cloud/coordination/fenced_placement.py)
    # and whose checkpoint is current (cloud/coordination/fenced_store.py). Empty: workers agree
    # through Zenoh liveliness alone (placement.py), which is not fenced against partitions.
    coordination: Annotated[str, ETCD_ENDPOINT] = ""
    # The coordination service's TLS folder (``fleetslam certs`` writes it as <lab>/etcd:
    # its CA, the workers' client certificate and key); with it the endpoint is https and
    # etcd takes only that certificate (docs/deployment.md). Empty: plain http.
    coordination_certs: Annotated[str, ANY_TEXT] = ""
    # Many workers with a coordination service (cloud/coordination/ownership.py): each worker's etcd
    # lease, in whole seconds (etcd's unit; 2 is its least). A worker that cannot renew it
    # stops serving 3/4 of it after its last renewal; its robots go to another worker once
    # etcd expires it, so a lost machine's robots fail over in about this.
    lease_s: Annotated[int, between(2, 600)] = 2
    # The lease is renewed by a process of its own (cloud/coordination/lease_keeper.py) only while
    # the worker shows it is alive: a worker stopped or frozen this long lets its lease go (its
    # robots fail over this plus lease_s later). Long enough for a loaded worker's beat.
    stall_s: Annotated[float, between(0.5, 600.0)] = 5.0
    # The Zenoh lease a worker announces to its router: the router drops the link of a
    # worker it has not heard from this long. Until then the router may wait on that link
    # (a reliable message blocks behind a full queue), holding up every robot's messages.
    # Keep-alives go 4 times per lease.
    zenoh_lease_s: Annotated[float, between(0.5, 600.0)] = 2.0
    # The etcd a run starts (cloud/coordination/coordination_service.py): healthy within this.
    coordination_start_s: Annotated[float, above(0.0)] = 10.0


@dataclass(frozen=True)
class ViewConfig:
    """The view in rerun: the cloud's live view (``cloud`` / ``demo`` with ``--view`` or
    ``--save``) and a finished run's (``fleetslam view``)."""

    # Updates waiting for the view's own logging thread; when it falls behind, new ones are
    # dropped (and counted): a robot's session never waits for the view.
    queue_size: Annotated[int, at_least(1)] = 2048
    # A robot's camera (frustum and pose) every n-th frame; its trajectory as line-strip
    # segments of this many frames (each logged once, never the whole trajectory again).
    pose_every_frames: Annotated[int, at_least(1)] = 1
    trajectory_segment_frames: Annotated[int, at_least(1)] = 10
    # Each keyframe's back-projected points, voxel-downsampled to this size, at most this
    # many per keyframe, so the growing map stays fluid in the viewer.
    keyframe_voxel_m: Annotated[float, above(0.0)] = 0.05
    max_points_per_keyframe: Annotated[int, at_least(1)] = 4000
    # A keyframe's points move with it (local BA, loop closing) once its pose changed by
    # more than this.
    move_translation_m: Annotated[float, at_least(0.0)] = 0.01
    move_rotation_deg: Annotated[float, at_least(0.0)] = 0.5
    # The merger's global transforms and inter-robot constraints at most this often
    # (each may re-optimise a joined group's pose graph, on the merger's thread).
    global_every_s: Annotated[float, above(0.0)] = 2.0
    # Link throughput per robot: bytes received, sampled this often.
    throughput_every_s: Annotated[float, above(0.0)] = 1.0
    # Without a display to spawn a viewer on, the cloud serves its view over gRPC here
    # (``rerun rerun+http://HOST:PORT/proxy``); loopback only unless changed. Not rerun's
    # 9876: a viewer started on the same machine opens its own server there.
    grpc_bind: Annotated[str, HOST] = "127.0.0.1"
    grpc_port: Annotated[int, between(1, 65535)] = 9877
    # Where --foxglove PORT serves the Foxglove app (loopback only unless changed).
    foxglove_host: Annotated[str, HOST] = "127.0.0.1"
    # What that server keeps for viewers that connect late (rerun's size syntax).
    server_memory_limit: Annotated[str, MEMORY_SIZE] = "1GiB"
    # A finished run's maps (fleetslam view): at most this many points each.
    max_map_points: Annotated[int, at_least(1)] = 2_000_000
    # At shutdown, the cloud waits at most this long for queued updates to be written.
    close_timeout_s: Annotated[float, at_least(0.0)] = 10.0


@dataclass(frozen=True)
class OutputsConfig:
    """Files every run writes besides its own (trajectories, maps, summary, report): one
    switch per extra output, the same for ``run``, ``demo`` and the cloud's ``merge``."""

    # ``run.mcap``: the run's trajectories, transforms, maps, OctoMap and inter-robot
    # constraints as ROS 2 messages (Foxglove, ``ros2 bag play``); about the size of the
    # run's PLY files, zstd-compressed.
    mcap: bool = True


# A Zenoh endpoint, or empty (off).
OPTIONAL_ENDPOINT = Text(lambda s: endpoint_problem(s) if s else None,
                         "empty, or a Zenoh endpoint PROTOCOL/ADDRESS, e.g. tcp/HOST:PORT")


@dataclass(frozen=True)
class Ros2OutConfig:
    """Results as live ROS 2 topics, published as an rmw_zenoh node publishes (ros2_out/):
    a robot's pose, TF, path and status (``fleetslam robot --ros2-out``)."""

    # The ROS 2 graph's Zenoh router (rmw_zenohd) to publish through; empty: no ROS 2
    # output. An unreachable router is said once; the robot tracks on and tries again.
    endpoint: Annotated[str, OPTIONAL_ENDPOINT] = ""
    # ROS_DOMAIN_ID of the graph; -1: the ROS_DOMAIN_ID environment variable (0 without).
    domain_id: Annotated[int, between(-1, 232)] = -1
    # The graph's ROS 2: keys carry REP-2016 type hashes from Iron on (jazzy), Humble's
    # rmw_zenoh a placeholder its subscribers match exactly (humble).
    distro: Annotated[str, OneOf(("jazzy", "humble"))] = "jazzy"
    # A Zenoh config file (JSON5) for the session to that router (TLS, ...); empty: a
    # client of the endpoint, no multicast, timestamps on (transient local needs them).
    zenoh_config: Annotated[str, ANY_TEXT] = ""
    # The frame every robot's map is placed in once the cloud joins it to a group (REP 105's
    # map); each robot's own map frame is <robot>/map.
    fleet_frame: Annotated[str, Text(lambda s: None if s.strip("/") else "must not be empty",
                                     "a TF frame name")] = "map"
    # The camera's TF frame; empty: the frame_id of its images when they came from ROS (a
    # bag, ROS 2 topics), else <robot>/camera.
    camera_frame: Annotated[str, ANY_TEXT] = ""
    # The robot's own TF (/tf, /tf_static on its graph) is kept this long behind its newest
    # stamp: where the camera's frame already has a parent there (odometry, its mounting),
    # fleetslam publishes <robot>/map -> the top of that tree (REP 105's map -> odom).
    tf_buffer_s: Annotated[float, above(0.0)] = 10.0
    # nav_msgs/Path of the tracked poses this often, at most this many (the newest).
    path_every_s: Annotated[float, above(0.0)] = 1.0
    path_max_poses: Annotated[int, at_least(1)] = 10000
    # diagnostic_msgs status (tracking / lost / relocalised, round trip, skipped) this often.
    diagnostics_every_s: Annotated[float, above(0.0)] = 1.0
    # Waiting for the router at start (then again every retry_s, in the background).
    connect_timeout_s: Annotated[float, above(0.0)] = 3.0
    retry_s: Annotated[float, above(0.0)] = 10.0
    # After its session ended, a robot keeps its ROS 2 node up this long: its last TF, and
    # the fleet frame a merge of its map sends (``placed``, final).
    hold_s: Annotated[float, at_least(0.0)] = 0.0


@dataclass(frozen=True)
class Config:
    """Every setting, by section. The algorithm parameters come first (orb, tracking,
    place_recognition, loop_closing, relocalisation, map, fshicp, merge, grid, planner:
    what is computed from the frames), then the deployment settings (source, synthetic,
    camera, wire, link, transport, placement, view, outputs, ros2_out: where frames come
    from, how robot and cloud talk, what a run shows and writes); ``SECTION_GROUPS``."""

    orb: OrbConfig = field(default_factory=OrbConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    place_recognition: PlaceRecognitionConfig = field(default_factory=PlaceRecognitionConfig)
    loop_closing: LoopClosingConfig = field(default_factory=LoopClosingConfig)
    relocalisation: RelocalisationConfig = field(default_factory=RelocalisationConfig)
    map: MapConfig = field(default_factory=MapConfig)
    fshicp: FsHicpConfig = field(default_factory=FsHicpConfig)
    merge: MergeConfig = field(default_factory=MergeConfig)
    grid: GridConfig = field(default_factory=GridConfig)
    planner: PlannerConfig = field(default_factory=PlannerConfig)
    source: SourceConfig = field(default_factory=SourceConfig)
    synthetic: SyntheticConfig = field(default_factory=SyntheticConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    wire: WireConfig = field(default_factory=WireConfig)
    link: LinkConfig = field(default_factory=LinkConfig)
    transport: TransportConfig = field(default_factory=TransportConfig)
    placement: PlacementConfig = field(default_factory=PlacementConfig)
    view: ViewConfig = field(default_factory=ViewConfig)
    outputs: OutputsConfig = field(default_factory=OutputsConfig)
    ros2_out: Ros2OutConfig = field(default_factory=Ros2OutConfig)

    def with_values(self, values: Mapping[str, Any], flag: str | None = None,
                    where: str = "settings") -> Config:
        """This config with ``values`` in place of its own (dotted keys:
        ``{"link.bandwidth_mbps": 5.0}``), each checked as ``load_config`` checks a TOML
        file's: ValueError naming ``where`` and the key, or ``flag`` when a command-line flag
        gave the value. The config itself never changes (frozen once loaded)."""
        return _updated(self, _tables(values), where, flag=flag)


# Config's sections, algorithm parameters apart from deployment settings (the order of
# ``fleetslam config`` and docs/config.md).
SECTION_GROUPS: dict[str, tuple[str, ...]] = {
    "Algorithm parameters": ("orb", "tracking", "place_recognition", "loop_closing",
                             "relocalisation", "map", "fshicp", "merge", "grid", "planner"),
    "Deployment settings": ("source", "synthetic", "camera", "wire", "link", "transport",
                            "placement", "view", "outputs", "ros2_out"),
}


def _updated(section: Any, values: Mapping[str, Any], where: str, prefix: str = "",
             flag: str | None = None) -> Any:
    """``section`` with ``values`` (a TOML table) in place of its own, each checked against
    its field's type and rule; ValueError naming ``where`` and the key (or ``flag``, the
    command-line flag that gave the value)."""
    rules = rules_of(type(section))
    changes: dict[str, Any] = {}
    for key, value in values.items():
        name = f"{prefix}{key}"
        if key not in rules:
            raise ValueError(f"{where}: unknown setting '{name}' (known: {', '.join(rules)})")
        current = getattr(section, key)
        if dataclasses.is_dataclass(current):
            if not isinstance(value, Mapping):
                raise ValueError(f"{where}: {name}: expected a table")
            changes[key] = _updated(current, value, where, f"{name}.", flag)
            continue
        try:
            changes[key] = checked(value, *rules[key])
        except ValueError as exc:
            blame = f"{flag} {value!r}" if flag else f"{where}: {name} = {value!r}"
            raise ValueError(f"{blame}: {exc}") from None
    return dataclasses.replace(section, **changes)


def _tables(values: Mapping[str, Any]) -> dict[str, Any]:
    """Dotted keys (``{"link.bandwidth_mbps": 5.0}``) as the nested tables a TOML file
    gives (``{"link": {"bandwidth_mbps": 5.0}}``)."""
    tables: dict[str, Any] = {}
    for dotted, value in values.items():
        *path, key = dotted.split(".")
        table = tables
        for name in path:
            table = table.setdefault(name, {})
        table[key] = value
    return tables


def check_config(section: Any, where: str, prefix: str = "") -> None:
    """Every value of a config (or one section) made elsewhere than from a TOML file (a
    checkpoint's), checked as ``load_config`` checks a file's; ValueError naming the key."""
    for key, (hint, rule) in rules_of(type(section)).items():
        value = getattr(section, key)
        if dataclasses.is_dataclass(value):
            check_config(value, where, f"{prefix}{key}.")
            continue
        try:
            checked(value, hint, rule)
        except ValueError as exc:
            raise ValueError(f"{where}: {prefix}{key} = {value!r}: {exc}") from None


def load_config(path: str | Path | None = None) -> Config:
    """Defaults, overridden by the TOML file at ``path`` if given."""
    config = Config()
    if path is not None:
        path = Path(path)
        try:
            values = tomllib.loads(path.read_text())
        except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
            raise ValueError(f"{path}: cannot read config: {exc}") from exc
        config = _updated(config, values, str(path))
    return config


def config_to_dict(config: Config) -> dict[str, Any]:
    return dataclasses.asdict(config)

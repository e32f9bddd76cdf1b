"""The fleet's map frame is REP 103 (mapping/map_frame.py): level on the floor the merge
finds, or the anchor's base_link from the camera's mounting; a lone robot's run has its
level global map too. Ground truth only checks the result."""

from __future__ import annotations

import numpy as np
import pytest

from fleetslam.camera import Camera
from fleetslam.config import Config, GridConfig, load_config
from fleetslam.io.ply import read_ply
from fleetslam.io.trajectory import read_tum_trajectory
from fleetslam.mapping.map_frame import T_base_camera, live_map_frame
from fleetslam.transforms import invert, make_T, rotation_exp, transform_points

# A camera looking forward, 0.2 m ahead of base_link and 1.1 m up, pitched down 10 degrees:
# optical (x right, y down, z forward) in base_link (x forward, y left, z up).
_OPTICAL = np.array([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]])
_PITCH = rotation_exp([0.0, np.radians(10.0), 0.0])
MOUNTING = make_T(_PITCH @ _OPTICAL, [0.2, 0.0, 1.1])


def _as_setting(T: np.ndarray) -> tuple[float, ...]:
    from fleetslam.transforms import quaternion_from_matrix

    return (*T[:3, 3], *quaternion_from_matrix(T[:3, :3])[0])


def test_the_merged_map_is_level_on_the_floor(synthetic_run, synthetic_scene):
    """The synthetic room's floor is its world's z = 0, z up: the fleet's map frame must be
    the same plane (within a degree and 3 cm), x along the first camera's view."""
    out, summary = synthetic_run
    _, folders = synthetic_scene
    merge = summary["merge"]
    assert merge["map_frame"]["source"] == "floor plane"
    anchor = merge["anchor"]
    _, gt = read_tum_trajectory(folders[int(anchor[1:])] / "groundtruth.txt")
    T_world_map = gt[0] @ np.array(merge["map_frame"]["T_anchor_map"])
    assert np.degrees(np.arccos(np.clip(T_world_map[2, 2], -1, 1))) < 1.0
    assert abs(T_world_map[2, 3]) < 0.03
    # The outputs are in it: the global trajectory's first pose is the anchor's first camera.
    _, poses = read_tum_trajectory(out / "global" / f"{anchor}.tum")
    np.testing.assert_allclose(poses[0], invert(np.array(merge["map_frame"]["T_anchor_map"])),
                               atol=1e-6)
    view = poses[0][:3, 2]  # the optical axis: forward, along x
    assert view[0] > 0 and abs(view[1]) < 1e-6
    # And the PLY: its floor points (world z near 0) are at map z near 0.
    points, _ = read_ply(out / "global_map.ply")
    world = transform_points(T_world_map, points)
    floor = np.abs(world[:, 2]) < 0.02
    assert floor.sum() > 1000 and np.abs(points[floor, 2]).max() < 0.06


def test_a_mounted_lone_robot_maps_in_its_base_link(tmp_path, synthetic_scene):
    """One robot with ``[camera] base_link``: the run writes the global map, OctoMap and
    grid of its lone map, in ``map`` = its base_link at its first frame."""
    from fleetslam.datasets.tum import RgbdSequence
    from fleetslam.system import run_fleet

    config, folders = synthetic_scene
    config = Config(synthetic=config.synthetic)
    config = config.with_values({"camera.base_link": _as_setting(MOUNTING)})
    summary = run_fleet([("r0", str(folders[0]), RgbdSequence(folders[0]))], config,
                        tmp_path / "run", show_progress=False)
    merge = summary["merge"]
    assert merge["members"] == ["r0"] and merge["not_merged"] == {}
    assert merge["map_frame"]["source"] == "camera mounting"
    np.testing.assert_allclose(np.array(merge["map_frame"]["T_anchor_map"]), invert(MOUNTING),
                               atol=1e-9)
    _, poses = read_tum_trajectory(tmp_path / "run" / "global" / "r0.tum")
    np.testing.assert_allclose(poses[0], MOUNTING, atol=1e-6)
    for name in ("global_map.ply", "global_map.bt", "global_map.pgm", "global_map.yaml"):
        assert (tmp_path / "run" / name).stat().st_size > 0
    # The grid lies level in map, on the floor found along the mounting's up.
    T_map_grid = np.array(merge["grid"]["T_map_grid"])
    assert np.degrees(np.arccos(np.clip(T_map_grid[2, 2], -1, 1))) < 12.0


def test_the_live_map_frame_from_the_mounting_or_the_configured_up():
    T = make_T(rotation_exp([0.2, -0.4, 0.1]), [1.0, 2.0, 3.0])
    plain = Camera(500.0, 500.0, 320.0, 240.0)
    frame = live_map_frame(T, plain, GridConfig())
    np.testing.assert_allclose(frame[:3, 2], T[:3, :3] @ [0, -1, 0], atol=1e-12)
    np.testing.assert_allclose(frame[:3, 3], T[:3, 3], atol=1e-12)
    assert abs(frame[:3, 0] @ frame[:3, 2]) < 1e-12 and np.linalg.det(frame[:3, :3]) > 0
    mounted = plain.mounted(_as_setting(MOUNTING))
    np.testing.assert_allclose(T_base_camera(mounted), MOUNTING, atol=1e-12)
    np.testing.assert_allclose(live_map_frame(T, mounted, GridConfig()), T @ invert(MOUNTING),
                               atol=1e-12)
    # The camera as the hello carries it keeps the mounting.
    assert Camera.from_dict(mounted.to_dict()).base_link == mounted.base_link


def test_a_bad_mounting_is_refused_naming_it(tmp_path, synthetic_scene):
    from fleetslam.datasets.tum import RgbdSequence
    from fleetslam.system import run_fleet

    camera = Camera(500.0, 500.0, 320.0, 240.0)
    with pytest.raises(ValueError, match=r"\[camera\] base_link quaternion .* not a rotation"):
        camera.mounted((0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="hello camera: base_link must be empty or 7"):
        Camera.from_dict({**camera.to_dict(), "base_link": [1.0, 2.0]}, "hello camera")
    path = tmp_path / "c.toml"
    path.write_text("[camera]\nbase_link = [0, 0, 0, 0, 0, 1]\n")
    with pytest.raises(ValueError, match=r"c.toml: camera.base_link .* expected a list of 7"):
        load_config(path)
    # A run is refused before it writes anything.
    _, folders = synthetic_scene
    config = Config().with_values({"camera.base_link": (0.0,) * 7})
    with pytest.raises(ValueError, match=r"\[camera\] base_link quaternion"):
        run_fleet([("r0", str(folders[0]), RgbdSequence(folders[0]))], config,
                  tmp_path / "run", show_progress=False)
    assert not (tmp_path / "run").exists()

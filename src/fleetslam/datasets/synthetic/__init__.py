"""Deterministic synthetic multi-robot RGB-D scenes: the data of ``fleetslam demo`` and of
fast tests.

A textured room (floor, walls, ceiling) with furniture made of boxes is ray cast with
numpy for every pixel at once. Robots walk smooth, bounded paths in the middle of the
room; they start looking at a common region (the middle of the +y wall) and then turn
apart, each sweeping its own side, so their maps overlap and can be merged.

World frame: z up, floor at z = 0, room centred on x = y = 0 (x along the first room
dimension). Cameras follow OpenCV (x right, y down, z forward); poses are
``T_world_camera``.

Modules, one job each (an arrow: imports):

- ``box``: Box, the oriented box all geometry is made of
- ``furniture``: the boxes of one piece of furniture of each kind (-> box)
- ``trajectories``: robot paths, the zone they stay in, frame times
- ``layout``: where furniture stands; why the common region is furnished as it is
  (-> box, furniture, trajectories)
- ``textures``: procedural face textures (TEXELS_PER_M)
- ``room``: Room, the shell, furniture and baked face textures; cached per process
  (-> box, layout, textures)
- ``render``: ray casting a noise-free view of a Room (-> box, room)
- ``sensor``: Kinect-like depth and colour noise
- ``scene_files``: writing, checking and reusing scene folders on disk (TUM layout,
  scene.json) (-> render, room, sensor, trajectories)

The names below are re-exported so that callers import from the package.
"""

from fleetslam.datasets.synthetic.box import Box
from fleetslam.datasets.synthetic.layout import ROBOT_CLEARANCE_M
from fleetslam.datasets.synthetic.render import RENDER_BLUR_SIGMA, render
from fleetslam.datasets.synthetic.room import MIN_ROOM_SIZE_M, Room
from fleetslam.datasets.synthetic.scene_files import (
    FORMAT_NAME,
    FORMAT_VERSION,
    ensure_scene,
    generate_scene,
    robot_folder_name,
    scene_camera,
    scene_matches,
)
from fleetslam.datasets.synthetic.sensor import (
    DEPTH_SCALE,
    MIN_SENSOR_DEPTH_M,
    RGB_NOISE_SIGMA,
    sensor_depth,
    sensor_rgb,
)
from fleetslam.datasets.synthetic.textures import TEXELS_PER_M, paint_texture
from fleetslam.datasets.synthetic.trajectories import robot_timestamps, robot_trajectories

__all__ = [
    "DEPTH_SCALE",
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "MIN_ROOM_SIZE_M",
    "MIN_SENSOR_DEPTH_M",
    "RENDER_BLUR_SIGMA",
    "RGB_NOISE_SIGMA",
    "ROBOT_CLEARANCE_M",
    "TEXELS_PER_M",
    "Box",
    "Room",
    "ensure_scene",
    "generate_scene",
    "paint_texture",
    "render",
    "robot_folder_name",
    "robot_timestamps",
    "robot_trajectories",
    "scene_camera",
    "scene_matches",
    "sensor_depth",
    "sensor_rgb",
]

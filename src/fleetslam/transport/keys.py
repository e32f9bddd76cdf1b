"""Every Zenoh key fleetslam uses, in one place.

    fleet/<robot>/frame      robot -> cloud  FRAME message: the state at the offloading point
                                             (best effort: the link may lose it)
    fleet/<robot>/keyframe   robot -> cloud  KEYFRAME message: a keyframe's RGB-D for the dense
                                             map (reliable: resent until acknowledged)
    fleet/<robot>/control    robot -> cloud  JSON: hello (open or resume the session), end
    fleet/<robot>/feedback   cloud -> robot  FEEDBACK message per tracked frame: pose, keyframe
    fleet/<robot>/reply      cloud -> robot  JSON: welcome, ack (keyframe stored), need, ended
    fleet/cloud/control      anyone -> cloud JSON: merge (register all finished maps), status
    fleet/cloud/reply        cloud -> anyone JSON: merged, status

A robot id is 1-64 characters of [A-Za-z0-9_-], so it is always one key chunk.
"""

from __future__ import annotations

from fleetslam.wire import envelope

ROOT = "fleet"
CLOUD = "cloud"  # reserved: not a robot id


def check_robot_id(robot_id: str) -> str:
    """The id itself (the same rule as the message header's), or ValueError."""
    envelope.check_robot_id(robot_id)
    if robot_id == CLOUD:
        raise ValueError(f"robot id '{CLOUD}' is reserved for the cloud's own keys")
    return robot_id


def frame(robot_id: str) -> str:
    return f"{ROOT}/{robot_id}/frame"


def keyframe(robot_id: str) -> str:
    return f"{ROOT}/{robot_id}/keyframe"


def control(robot_id: str) -> str:
    return f"{ROOT}/{robot_id}/control"


def feedback(robot_id: str) -> str:
    return f"{ROOT}/{robot_id}/feedback"


def reply(robot_id: str) -> str:
    return f"{ROOT}/{robot_id}/reply"


# What the cloud subscribes to (one wildcard per kind), and its own control pair.
ALL_FRAMES = f"{ROOT}/*/frame"
ALL_KEYFRAMES = f"{ROOT}/*/keyframe"
ALL_CONTROL = f"{ROOT}/*/control"
CLOUD_CONTROL = control(CLOUD)
CLOUD_REPLY = reply(CLOUD)


def robot_of(key: str) -> str:
    """The robot id chunk of ``fleet/<robot>/<kind>`` (ValueError if it is not one)."""
    parts = key.split("/")
    if len(parts) != 3 or parts[0] != ROOT:
        raise ValueError(f"key {key!r} is not {ROOT}/<robot>/<kind>")
    return parts[1]

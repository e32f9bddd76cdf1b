"""Every Zenoh key fleetslam uses, in one place.

    fleet/<robot>/frame      robot -> cloud  FRAME message: the state at the offloading point
                                             (best effort: the link may lose it)
    fleet/<robot>/keyframe   robot -> cloud  KEYFRAME message: a keyframe's RGB-D for the dense
                                             map (reliable: resent until acknowledged)
    fleet/<robot>/control    robot -> cloud  JSON: hello (open or resume the session), end
    fleet/<robot>/feedback   cloud -> robot  FEEDBACK message per tracked frame: pose, keyframe
    fleet/<robot>/reply      cloud -> robot  JSON: welcome, ack (keyframe stored), need, ended
    fleet/cloud/control      operator -> cloud JSON: merge (register all finished maps), status
    fleet/cloud/reply        cloud -> operator JSON: merged, status

(who may use which key: transport/access_control.py)

Cloud workers agree among themselves with Zenoh liveliness tokens (no payload: a token is
there while its worker's Zenoh session lives, and vanishes when the worker dies):

    fleet/cloud/workers/<worker>           a worker is up
    fleet/cloud/claims/<robot>/<rank>      a worker bids to serve a robot (rank = its load
                                           and id: the lowest bid wins)
    fleet/cloud/owners/<robot>/<worker>    the worker that serves the robot

and the workers that do not merge publish each new keyframe of their robots for the one that
does (wire/merger_keyframes.py: a keyframe summary, its robot's keyframe poses and camera):

    fleet/cloud/keyframes/<robot>          worker -> the merging worker

A robot id is 1-64 characters of [A-Za-z0-9_-], so it is always one key chunk.
"""

from __future__ import annotations

from fleetslam.wire import envelope

ROOT = "fleet"
CLOUD = "cloud"  # reserved: not a robot id
# A robot's files are <run or store>/<robot>/: not the folders a run keeps beside them.
RUN_FOLDERS = ("global", "map", "report", "logs", "tls", "etcd")


def check_robot_id(robot_id: str) -> str:
    """The id itself (the same rule as the message header's), or ValueError."""
    envelope.check_robot_id(robot_id)
    if robot_id == CLOUD:
        raise ValueError(f"robot id '{CLOUD}' is reserved for the cloud's own keys")
    if robot_id in RUN_FOLDERS:
        raise ValueError(f"robot id {robot_id!r} is reserved: a run keeps its {robot_id}/ "
                         f"folder beside the robots' ({', '.join(RUN_FOLDERS)} are taken)")
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


WORKERS = f"{ROOT}/{CLOUD}/workers"
# Keyframe summaries a worker publishes for the worker that merges (cloud/merge/merger_service.py).
MERGE_KEYFRAMES = f"{ROOT}/{CLOUD}/keyframes"
CLAIMS = f"{ROOT}/{CLOUD}/claims"
OWNERS = f"{ROOT}/{CLOUD}/owners"
# Each worker's measured load (cloud/coordination/worker_load.py).
LOADS = f"{ROOT}/{CLOUD}/load"


def check_worker_id(worker_id: str) -> str:
    """A worker id is a key chunk with a robot id's characters (ValueError if not)."""
    envelope.check_robot_id(worker_id)
    return worker_id


def worker(worker_id: str) -> str:
    return f"{WORKERS}/{worker_id}"


def claim(robot_id: str, rank: str) -> str:
    return f"{CLAIMS}/{robot_id}/{rank}"


def load(worker_id: str) -> str:
    return f"{LOADS}/{worker_id}"


def owner(robot_id: str, worker_id: str) -> str:
    return f"{OWNERS}/{robot_id}/{worker_id}"


def last_chunks(key: str, n: int) -> list[str]:
    """The last ``n`` chunks of a key (a liveliness token's robot and worker)."""
    return str(key).split("/")[-n:]


def merge_keyframe(robot_id: str) -> str:
    return f"{MERGE_KEYFRAMES}/{robot_id}"


def robot_of(key: str) -> str:
    """The robot id chunk of ``fleet/<robot>/<kind>`` (ValueError if it is not one)."""
    parts = key.split("/")
    if len(parts) != 3 or parts[0] != ROOT:
        raise ValueError(f"key {key!r} is not {ROOT}/<robot>/<kind>")
    return parts[1]

"""The control protocol between robots, the cloud and command-line clients: every JSON
control message, its builder and its parser, in one place (binary frame and keyframe
messages are wire/).

Robot <-> cloud, on ``fleet/<robot>/control`` and ``fleet/<robot>/reply``:
    hello -> welcome | error;  end -> ending, then need (resend these keyframes) | ended;
    a worker taking the session over (its worker died) -> welcome (taken_over, unasked);
    each keyframe upload -> ack;  each frame decoded -> held (a reference for inter-frame
    coding);  a rejected message -> error (with a code and a reason);  unasked, whenever
    the merger places the robot's map in a group's frame or moves it -> placed.
Client <-> cloud, on ``fleet/cloud/control`` and ``fleet/cloud/reply``:
    status -> status;  merge -> merged | error.  A client request carries an ``id`` that its
    reply repeats; the client resends the same request until the reply comes (a lost request
    costs one resend interval, never a hang), and the cloud answers a repeated merge id from
    the merge already running or done instead of merging again.
"""

from __future__ import annotations

import json
import uuid
from dataclasses import dataclass
from enum import Enum
from typing import Any

import numpy as np

from fleetslam.camera import Camera
from fleetslam.pipeline.split import CLOUD_TRACKS, SUPPORTED_POINTS
from fleetslam.validation.names import name_problem

PROTOCOL = 1
# Control messages are small JSON; anything bigger is not one.
MAX_CONTROL_BYTES = 1 << 20


class Code(str, Enum):
    """Why the cloud said no (``error`` replies carry one)."""

    BAD_MESSAGE = "bad_message"  # not a valid control message
    NO_SESSION = "no_session"  # send a hello first
    REFUSED = "refused"  # valid, but the cloud will not (limits, a changed point)
    REJECTED = "rejected"  # a frame or keyframe message was dropped, with the reason
    # An upload of a frame the session does not hold as a keyframe (a cloud restarted from
    # a checkpoint older than it): it never will, so the robot stops resending it.
    NOT_A_KEYFRAME = "not_a_keyframe"
    UNKNOWN_TYPE = "unknown_type"
    # An inter-coded frame names a reference frame the session does not hold (a restart, a
    # closed session): the robot sends intra frames until new references are acknowledged.
    REFERENCE_MISSING = "reference_missing"
    FAILED = "failed"  # the cloud tried and failed (e.g. a merge)
    # The robot's session holds its memory budget: frames and uploads beyond it are dropped
    # unread (an upload is resent until acknowledged). Keep to max_frames_in_flight.
    OVER_BUDGET = "over_budget"


def encode(message: dict[str, Any]) -> bytes:
    return json.dumps(message).encode()


def parse_control(data: bytes) -> dict[str, Any]:
    """A control message as a dict with a string ``type``; ValueError saying what is wrong."""
    if len(data) > MAX_CONTROL_BYTES:
        raise ValueError(f"control message of {len(data)} bytes (limit {MAX_CONTROL_BYTES})")
    try:
        message = json.loads(data)
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"control message is not JSON: {exc}") from exc
    except RecursionError:
        raise ValueError("control message is nested too deeply") from None
    if not isinstance(message, dict) or not isinstance(message.get("type"), str):
        raise ValueError("control message must be a JSON object with a string 'type'")
    return message


@dataclass
class Hello:
    """A robot opening (or resuming) its session."""

    offload_at: int
    camera: Camera
    source: str
    # The robot re-plans while it runs: its frames may come at any point the cloud tracks
    # at (0-3), frame by frame (the session holds the map at all of them).
    adaptive: bool = False

    @staticmethod
    def parse(message: dict[str, Any]) -> "Hello":
        if message.get("protocol") != PROTOCOL:
            raise ValueError(f"protocol {message.get('protocol')!r} not supported "
                             f"(this cloud speaks {PROTOCOL})")
        k = message.get("offload_at")
        if isinstance(k, bool) or k not in SUPPORTED_POINTS:
            raise ValueError(f"offloading point {k!r} not supported; use one of "
                             f"{', '.join(map(str, SUPPORTED_POINTS))}")
        camera = message.get("camera")
        if not isinstance(camera, dict):
            raise ValueError("hello camera must be an object")
        camera = Camera.from_dict(camera, "hello camera")
        adaptive = message.get("adaptive", False)
        if not isinstance(adaptive, bool):
            raise ValueError(f"adaptive must be true or false, got {adaptive!r}")
        if adaptive and k not in CLOUD_TRACKS:
            raise ValueError(f"an adaptive robot switches among points "
                             f"{', '.join(map(str, CLOUD_TRACKS))}; it cannot start at {k}")
        source = message.get("source", "")
        if not isinstance(source, str):
            raise ValueError("hello source must be a string")
        return Hello(int(k), camera, source, adaptive)

    def message(self, frames: int | None) -> dict[str, Any]:
        """``frames``: how many the robot will send, None from a live camera (unknown until
        it stops). Informational: the cloud's progress and resume go by what it tracked."""
        return {"type": "hello", "protocol": PROTOCOL, "offload_at": self.offload_at,
                "adaptive": self.adaptive, "camera": self.camera.to_dict(),
                "source": self.source, "frames": frames}


# -- robot <-> cloud ------------------------------------------------------------------------

def welcome(resumed: bool, next_index: int, next_seq: int, keyframes_stored: int,
            reference_frames: int = 0, taken_over: bool = False,
            last_timestamp: float | None = None, history_lost: str | None = None
            ) -> dict[str, Any]:
    # reference_frames: the decoded frames the session keeps as references for inter-coded
    # frames (wire/inter.py); a cloud that says nothing (older) takes intra frames only.
    # taken_over: unasked, from a worker that restored the session after its worker died.
    # last_timestamp: of the session's last tracked frame (None: none yet); a resumed live
    # camera cannot seek to next_index, so it drops frames not after this moment.
    # history_lost: the robot's stored session could not be restored (why, and where its
    # checkpoint was kept): this is a fresh session, the frames before are not in it.
    message = {"type": "welcome", "resumed": resumed, "next_index": next_index,
               "next_seq": next_seq, "keyframes_stored": keyframes_stored,
               "reference_frames": reference_frames, "last_timestamp": last_timestamp}
    if history_lost is not None:
        message["history_lost"] = history_lost
    return {**message, "taken_over": True} if taken_over else message


def end(last_seq: int, keyframe_poses: dict[str, list] | None = None,
        camera: dict[str, Any] | None = None, unavailable: list[int] | None = None
        ) -> dict[str, Any]:
    """``camera``: a live source's counts (``source``, ``delivered``, ``taken``, ``skipped``:
    frames it delivered that the robot, busy, never took), for the summary; ``unavailable``: keyframes
    the robot cannot upload (a live camera keeps no recording): mapped without images."""
    message: dict[str, Any] = {"type": "end", "last_seq": last_seq}
    if keyframe_poses is not None:
        message["keyframe_poses"] = keyframe_poses
    if camera is not None:
        message["camera"] = camera
    if unavailable:
        message["unavailable"] = unavailable
    return message


def end_camera(message: dict[str, Any]) -> dict[str, Any] | None:
    """An ``end`` message's live camera counts, or None (a recording); ValueError saying
    what is wrong."""
    camera = message.get("camera")
    if camera is None:
        return None
    if not isinstance(camera, dict) or not isinstance(camera.get("source"), str) \
            or len(camera["source"]) > 200:
        raise ValueError("bad camera counts: not an object with a source name")
    for name in ("delivered", "taken", "skipped"):
        value = camera.get(name)
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise ValueError(f"bad camera counts: {name} {value!r} is not a count")
    return {name: camera[name] for name in ("source", "delivered", "taken", "skipped")}


def end_unavailable(message: dict[str, Any]) -> set[int]:
    """An ``end`` message's keyframes the robot cannot upload; ValueError if malformed."""
    frames = message.get("unavailable") or []
    if not isinstance(frames, list) or not all(
            isinstance(i, int) and not isinstance(i, bool) and i >= 0 for i in frames):
        raise ValueError("bad unavailable keyframes: not a list of frame indices")
    return set(frames)


def keyframe_poses(message: dict[str, Any]) -> dict[int, np.ndarray]:
    """An ``end`` message's keyframe poses (frame index -> 4 x 4); ValueError saying what is
    wrong."""
    poses = message.get("keyframe_poses") or {}
    if not isinstance(poses, dict):  # a list has no .items(): AttributeError otherwise
        raise ValueError("bad keyframe poses: not an object of frame index -> pose")
    out: dict[int, np.ndarray] = {}
    try:
        for index, T in poses.items():
            out[int(index)] = np.asarray(T, float).reshape(4, 4)
    except (TypeError, ValueError, OverflowError) as exc:  # OverflowError: 1e400-digit ints
        raise ValueError(f"bad keyframe poses: {exc}") from None
    # Recorded as the robot's own poses, as they are: like a frame's (wire/frames.py).
    if not all(np.isfinite(T).all() for T in out.values()):
        raise ValueError("bad keyframe poses: not finite")
    return out


def ending() -> dict[str, Any]:
    return {"type": "ending"}


def need(frames: list[int]) -> dict[str, Any]:
    return {"type": "need", "frames": frames}


def ended(summary: dict[str, Any]) -> dict[str, Any]:
    return {"type": "ended", "summary": summary}


def ack(frame_index: int) -> dict[str, Any]:
    return {"type": "ack", "frame_index": frame_index}


def held(seq: int) -> dict[str, Any]:
    # Frame ``seq`` is decoded and in the session's reference ring: later frames may be
    # coded against it (sent on arrival, before tracking, which may lag far behind).
    return {"type": "held", "seq": seq}


def error(code: Code, reason: str, **extra: Any) -> dict[str, Any]:
    return {"type": "error", "code": code.value, "reason": reason, **extra}


# A placement's rotation may be this far from orthonormal (JSON carries float64 exactly;
# a graph's rotations are orthonormal to ~1e-15).
PLACED_ORTHONORMAL_TOLERANCE = 1e-6


def placed(group: str, T_global_map: np.ndarray, final: bool) -> dict[str, Any]:
    """Where the robot's map frame lies in its group's frame (``group``: the robot whose
    first camera that frame is); ``final``: from a merge's written outputs (summary.json's
    T_global_map), not the live graph's."""
    return {"type": "placed", "group": group,
            "T_global_map": np.asarray(T_global_map, np.float64).tolist(), "final": final}


@dataclass(frozen=True)
class Placed:
    group: str
    T_global_map: np.ndarray  # 4 x 4, rigid
    final: bool


def parse_placed(message: dict[str, Any]) -> Placed:
    """A ``placed`` message; ValueError saying what is wrong (before anything is used)."""
    group = message.get("group")
    if not isinstance(group, str) or (problem := name_problem(group)):
        raise ValueError(f"placed: group {group!r} is not a robot id"
                         + (f" ({problem})" if isinstance(group, str) else ""))
    final = message.get("final")
    if not isinstance(final, bool):
        raise ValueError(f"placed: final must be true or false, got {final!r}")
    rows = message.get("T_global_map")
    if not isinstance(rows, list) or len(rows) != 4 or not all(
            isinstance(r, list) and len(r) == 4 and all(
                isinstance(v, (int, float)) and not isinstance(v, bool) for v in r)
            for r in rows):
        raise ValueError("placed: T_global_map is not 4 rows of 4 numbers")
    try:
        T = np.array(rows, np.float64)
    except OverflowError:  # an integer of 400 digits
        raise ValueError("placed: T_global_map is not finite") from None
    if not np.isfinite(T).all():
        raise ValueError("placed: T_global_map is not finite")
    R = T[:3, :3]
    if not np.array_equal(T[3], [0.0, 0.0, 0.0, 1.0]) or \
            np.abs(R @ R.T - np.eye(3)).max() > PLACED_ORTHONORMAL_TOLERANCE or \
            np.linalg.det(R) < 0:
        raise ValueError("placed: T_global_map is not a rigid transform (a rotation and a "
                         "translation, last row 0 0 0 1)")
    return Placed(group, T, final)


# -- client <-> cloud -----------------------------------------------------------------------

def request(kind: str, request_id: str | None = None) -> dict[str, Any]:
    """A client's ``status`` or ``merge`` request, with a fresh id unless one is given."""
    if kind not in ("status", "merge"):
        raise ValueError(f"unknown request {kind!r}")
    return {"type": kind, "id": request_id or uuid.uuid4().hex}


def request_id(message: dict[str, Any]) -> str | None:
    rid = message.get("id")
    return rid if isinstance(rid, str) and 0 < len(rid) <= 64 else None


def status(request_id: str | None, robots: dict[str, Any], merge: dict[str, Any],
           **worker: Any) -> dict[str, Any]:
    """One worker's answer: its robots and merger, and (``worker``) its id, the live
    workers and the placement table it knows; a client gathers every worker's answer."""
    return {"type": "status", "id": request_id, "robots": robots, "merge": merge, **worker}


def merged(request_id: str | None, summary: dict[str, Any]) -> dict[str, Any]:
    return {"type": "merged", "id": request_id, "summary": summary}

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

Every message is a frozen dataclass: ``message()`` is its JSON object, ``parse`` checks one
read from JSON before anything uses it (ValueError saying what is wrong); ``parse_reply``
reads any reply a robot hears.
"""

from __future__ import annotations

import json
import uuid
from dataclasses import dataclass, field
from enum import Enum
from typing import Any, ClassVar

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
    # A hello for a session that ended: a finished session is never resumed (its trajectory
    # and map stay as written); a new run starts under a new robot id.
    SESSION_ENDED = "session_ended"


def encode(message: Any) -> bytes:
    """A message object's (or a JSON object's) bytes."""
    return json.dumps(message.message() if hasattr(message, "message") else message).encode()


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
    # The robot is placed in the cloud's loaded map and never moves nor extends it
    # (localisation only, for this robot). A class-level default: a checkpoint written
    # before this field restores with it off.
    localise_only: bool = False

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
        localise_only = message.get("localise_only", False)
        if not isinstance(localise_only, bool):
            raise ValueError(f"localise_only must be true or false, got {localise_only!r}")
        return Hello(int(k), camera, source, adaptive, localise_only)

    def message(self, frames: int | None) -> dict[str, Any]:
        """``frames``: how many the robot will send, None from a live camera (unknown until
        it stops). Informational: the cloud's progress and resume go by what it tracked."""
        return {"type": "hello", "protocol": PROTOCOL, "offload_at": self.offload_at,
                "adaptive": self.adaptive, "camera": self.camera.to_dict(),
                "source": self.source, "frames": frames, "localise_only": self.localise_only}


# -- robot <-> cloud ------------------------------------------------------------------------

def _int(message: dict[str, Any], key: str, default: int | None = None) -> int:
    """A non-negative integer field; ValueError naming it."""
    value = message.get(key, default)
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise ValueError(f"{message.get('type')}: {key} {value!r} is not a count or index")
    return value


def _str(message: dict[str, Any], key: str, limit: int = 4096) -> str | None:
    value = message.get(key)
    if value is not None and (not isinstance(value, str) or len(value) > limit):
        raise ValueError(f"{message.get('type')}: {key} is not a string of at most {limit}")
    return value


@dataclass(frozen=True)
class Welcome:
    """The cloud opened (or resumed) the robot's session."""

    TYPE: ClassVar[str] = "welcome"
    resumed: bool
    next_index: int
    next_seq: int
    keyframes_stored: int
    # The decoded frames the session keeps as references for inter-coded frames
    # (wire/inter.py); a cloud that says nothing (older) takes intra frames only.
    reference_frames: int = 0
    # Unasked, from a worker that restored the session after its worker died.
    taken_over: bool = False
    # Of the session's last tracked frame (None: none yet); a resumed live camera cannot
    # seek to next_index, so it drops frames not after this moment.
    last_timestamp: float | None = None
    # The robot's stored session could not be restored (why, and where its checkpoint was
    # kept): this is a fresh session, the frames before are not in it.
    history_lost: str | None = None
    # A robot that tracks itself may send its keyframes' poses as deltas
    # (wire/pose_deltas.py); a cloud that says nothing (older) takes them whole.
    pose_deltas: bool = False

    def message(self) -> dict[str, Any]:
        message = {"type": self.TYPE, "resumed": self.resumed, "next_index": self.next_index,
                   "next_seq": self.next_seq, "keyframes_stored": self.keyframes_stored,
                   "reference_frames": self.reference_frames,
                   "last_timestamp": self.last_timestamp, "pose_deltas": self.pose_deltas}
        if self.history_lost is not None:
            message["history_lost"] = self.history_lost
        return {**message, "taken_over": True} if self.taken_over else message

    @staticmethod
    def parse(message: dict[str, Any]) -> Welcome:
        last = message.get("last_timestamp")
        if last is not None and (isinstance(last, bool) or not isinstance(last, (int, float))
                                 or not np.isfinite(last)):
            raise ValueError(f"welcome: last_timestamp {last!r} is not a time")
        return Welcome(message.get("resumed") is True, _int(message, "next_index", 0),
                       _int(message, "next_seq"), _int(message, "keyframes_stored", 0),
                       _int(message, "reference_frames", 0), message.get("taken_over") is True,
                       None if last is None else float(last), _str(message, "history_lost"),
                       message.get("pose_deltas") is True)


@dataclass(frozen=True)
class End:
    """The robot is done: its last seq; at point 6 its keyframes' poses (frame index ->
    4 x 4, its own map's); a live source's counts (``source``, ``delivered``, ``taken``,
    ``skipped``: frames it delivered that the robot, busy, never took), for the summary;
    the keyframes it cannot upload (a live camera keeps no recording): mapped without
    images."""

    TYPE: ClassVar[str] = "end"
    last_seq: int
    keyframe_poses: dict[int, np.ndarray] = field(default_factory=dict)
    camera: dict[str, Any] | None = None
    unavailable: frozenset[int] = frozenset()

    def message(self) -> dict[str, Any]:
        message: dict[str, Any] = {"type": self.TYPE, "last_seq": self.last_seq}
        if self.keyframe_poses:
            message["keyframe_poses"] = {str(i): np.asarray(T).tolist()
                                         for i, T in self.keyframe_poses.items()}
        if self.camera is not None:
            message["camera"] = self.camera
        if self.unavailable:
            message["unavailable"] = sorted(self.unavailable)
        return message

    @staticmethod
    def last_seq_of(message: dict[str, Any]) -> int | None:
        """The end's last seq as sent, if it is one (read before the rest is checked: an
        end waits for its frames in flight either way)."""
        seq = message.get("last_seq")
        return seq if isinstance(seq, int) and not isinstance(seq, bool) else None

    @staticmethod
    def parse(message: dict[str, Any]) -> End:
        seq = End.last_seq_of(message)
        return End(-1 if seq is None else seq, _end_keyframe_poses(message),
                   _end_camera(message), _end_unavailable(message))


def _end_camera(message: dict[str, Any]) -> dict[str, Any] | None:
    camera = message.get("camera")
    if camera is None:
        return None
    if not isinstance(camera, dict) or not isinstance(camera.get("source"), str) \
            or len(camera["source"]) > 200:
        raise ValueError("bad camera counts: not an object with a source name")
    # "undelivered" (frames the camera produced and never delivered) is newer: optional.
    names = ("delivered", "taken", "skipped", *(("undelivered",) if "undelivered" in camera
                                                else ()))
    for name in names:
        value = camera.get(name)
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise ValueError(f"bad camera counts: {name} {value!r} is not a count")
    return {name: camera[name] for name in ("source", *names)}


def _end_unavailable(message: dict[str, Any]) -> frozenset[int]:
    frames = message.get("unavailable") or []
    if not isinstance(frames, list) or not all(
            isinstance(i, int) and not isinstance(i, bool) and i >= 0 for i in frames):
        raise ValueError("bad unavailable keyframes: not a list of frame indices")
    return frozenset(frames)


def _end_keyframe_poses(message: dict[str, Any]) -> dict[int, np.ndarray]:
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


@dataclass(frozen=True)
class Ending:
    """The cloud heard the end; need or ended follows once its frames are done."""

    TYPE: ClassVar[str] = "ending"

    def message(self) -> dict[str, Any]:
        return {"type": self.TYPE}

    @staticmethod
    def parse(message: dict[str, Any]) -> Ending:
        return Ending()


@dataclass(frozen=True)
class Need:
    """Resend these keyframes' uploads (frame indices), then end again."""

    TYPE: ClassVar[str] = "need"
    frames: tuple[int, ...]

    def message(self) -> dict[str, Any]:
        return {"type": self.TYPE, "frames": list(self.frames)}

    @staticmethod
    def parse(message: dict[str, Any]) -> Need:
        frames = message.get("frames")
        if not isinstance(frames, list) or not all(
                isinstance(i, int) and not isinstance(i, bool) and i >= 0 for i in frames):
            raise ValueError("need: frames is not a list of frame indices")
        return Need(tuple(frames))


@dataclass(frozen=True)
class Ended:
    """The robot's session is finished and durable; its summary (summary.json's robot)."""

    TYPE: ClassVar[str] = "ended"
    summary: dict[str, Any]

    def message(self) -> dict[str, Any]:
        return {"type": self.TYPE, "summary": self.summary}

    @staticmethod
    def parse(message: dict[str, Any]) -> Ended:
        summary = message.get("summary")
        if not isinstance(summary, dict):
            raise ValueError("ended: summary is not an object")
        return Ended(summary)


@dataclass(frozen=True)
class Ack:
    """A keyframe's upload is stored and a checkpoint covers it."""

    TYPE: ClassVar[str] = "ack"
    frame_index: int

    def message(self) -> dict[str, Any]:
        return {"type": self.TYPE, "frame_index": self.frame_index}

    @staticmethod
    def parse(message: dict[str, Any]) -> Ack:
        return Ack(_int(message, "frame_index"))


@dataclass(frozen=True)
class Held:
    """Frame ``seq`` is decoded and in the session's reference ring: later frames may be
    coded against it (sent on arrival, before tracking, which may lag far behind)."""

    TYPE: ClassVar[str] = "held"
    seq: int

    def message(self) -> dict[str, Any]:
        return {"type": self.TYPE, "seq": self.seq}

    @staticmethod
    def parse(message: dict[str, Any]) -> Held:
        return Held(_int(message, "seq"))


@dataclass(frozen=True)
class Error:
    """Why the cloud said no (``code``) in words (``reason``), and what it answers."""

    TYPE: ClassVar[str] = "error"
    code: str
    reason: str
    answer_to: str | None = None  # "hello" or "end": a refusal of that message
    rejected: str | None = None  # "frame", "keyframe", "control": what was dropped
    frame_index: int | None = None  # an upload's frame (not_a_keyframe, over budget)
    seq: int | None = None  # reference_missing: the frame that named a missing reference
    missing: tuple[int, ...] | None = None  # ... and the references it named
    full: bool = False  # no session slot free: may free up
    wait: bool = False  # the cloud cannot serve yet: may change
    max_sessions: int | None = None
    id: str | None = None  # a client request's id

    def message(self) -> dict[str, Any]:
        message: dict[str, Any] = {"type": self.TYPE, "code": self.code, "reason": self.reason}
        for name in ("answer_to", "rejected", "frame_index", "seq", "missing", "max_sessions",
                     "id"):
            value = getattr(self, name)
            if value is not None:
                message[name] = list(value) if name == "missing" else value
        if self.full:
            message["full"] = True
        if self.wait:
            message["wait"] = True
        return message

    @staticmethod
    def of(code: Code, reason: str, **extra: Any) -> Error:
        return Error(code.value, reason, **extra)

    @staticmethod
    def parse(message: dict[str, Any]) -> Error:
        missing = message.get("missing")
        if missing is not None and (not isinstance(missing, list) or not all(
                isinstance(i, int) and not isinstance(i, bool) for i in missing)):
            raise ValueError("error: missing is not a list of seqs")
        optional = {k: _int(message, k) if message.get(k) is not None else None
                    for k in ("frame_index", "seq", "max_sessions")}
        return Error(_str(message, "code", 64) or "", _str(message, "reason") or "",
                     _str(message, "answer_to", 16), _str(message, "rejected", 16),
                     missing=None if missing is None else tuple(missing),
                     full=message.get("full") is True, wait=message.get("wait") is True,
                     id=request_id(message), **optional)


# A placement's rotation may be this far from orthonormal (JSON carries float64 exactly;
# a graph's rotations are orthonormal to ~1e-15).
PLACED_ORTHONORMAL_TOLERANCE = 1e-6


@dataclass(frozen=True)
class Placed:
    """Where the robot's map frame lies in its group's frame (``group``: the robot whose
    first camera that frame is); ``final``: from a merge's written outputs (summary.json's
    T_global_map), not the live graph's."""

    TYPE: ClassVar[str] = "placed"
    group: str
    T_global_map: np.ndarray  # 4 x 4, rigid
    final: bool

    def message(self) -> dict[str, Any]:
        return {"type": self.TYPE, "group": self.group,
                "T_global_map": np.asarray(self.T_global_map, np.float64).tolist(),
                "final": self.final}

    @staticmethod
    def parse(message: dict[str, Any]) -> Placed:
        return parse_placed(message)


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

@dataclass(frozen=True)
class Request:
    """A client's ``status`` or ``merge`` request, with a fresh id unless one is given."""

    KINDS: ClassVar[tuple[str, ...]] = ("status", "merge")
    kind: str
    id: str | None = field(default_factory=lambda: uuid.uuid4().hex)

    def __post_init__(self) -> None:
        if self.kind not in self.KINDS:
            raise ValueError(f"unknown request {self.kind!r}")

    def message(self) -> dict[str, Any]:
        return {"type": self.kind, "id": self.id}

    @staticmethod
    def parse(message: dict[str, Any]) -> Request:
        """ValueError for a type that is no request; an id that is no id is None (the
        reply cannot carry it)."""
        return Request(message["type"], request_id(message))


def request_id(message: dict[str, Any]) -> str | None:
    rid = message.get("id")
    return rid if isinstance(rid, str) and 0 < len(rid) <= 64 else None


@dataclass(frozen=True)
class StatusReply:
    """One worker's answer: its robots and merger, its id, the live workers and the
    placement table it knows; a client gathers every worker's answer."""

    TYPE: ClassVar[str] = "status"
    id: str | None
    robots: dict[str, Any]
    merge: dict[str, Any]
    worker: str | None = None
    workers: list[str] = field(default_factory=list)
    placement: dict[str, str] = field(default_factory=dict)
    elections: dict[str, int] = field(default_factory=dict)

    def message(self) -> dict[str, Any]:
        return {"type": self.TYPE, "id": self.id, "robots": self.robots, "merge": self.merge,
                "worker": self.worker, "workers": self.workers, "placement": self.placement,
                "elections": self.elections}

    @staticmethod
    def parse(message: dict[str, Any]) -> StatusReply:
        parts = {k: message.get(k) for k in ("robots", "merge", "placement", "elections")}
        if not all(isinstance(v, dict) for v in parts.values()):
            raise ValueError("status: robots, merge, placement and elections must be objects")
        workers = message.get("workers")
        if not isinstance(workers, list) or not all(isinstance(w, str) for w in workers):
            raise ValueError("status: workers is not a list of worker ids")
        return StatusReply(request_id(message), parts["robots"], parts["merge"],
                           _str(message, "worker", 256), workers, parts["placement"],
                           parts["elections"])


@dataclass(frozen=True)
class Merged:
    """The merge a client asked for is written: summary.json's content."""

    TYPE: ClassVar[str] = "merged"
    id: str | None
    summary: dict[str, Any]

    def message(self) -> dict[str, Any]:
        return {"type": self.TYPE, "id": self.id, "summary": self.summary}

    @staticmethod
    def parse(message: dict[str, Any]) -> Merged:
        summary = message.get("summary")
        if not isinstance(summary, dict):
            raise ValueError("merged: summary is not an object")
        return Merged(request_id(message), summary)


OperatorReply = StatusReply | Merged | Error
OPERATOR_REPLIES: dict[str, Any] = {kind.TYPE: kind for kind in (StatusReply, Merged, Error)}


def parse_operator_reply(data: bytes) -> OperatorReply:
    """A cloud's answer to a client's request, checked; ValueError saying what is wrong."""
    message = parse_control(data)
    kind = OPERATOR_REPLIES.get(message["type"])
    if kind is None:
        raise ValueError(f"unknown reply {message['type'][:40]!r}")
    return kind.parse(message)


Reply = Welcome | Ending | Need | Ended | Ack | Held | Error | Placed
REPLIES: dict[str, Any] = {kind.TYPE: kind for kind in
                           (Welcome, Ending, Need, Ended, Ack, Held, Error, Placed)}


class BadReply(ValueError):
    """A reply that does not parse; ``kind``: its type, if it named a known one."""

    def __init__(self, reason: str, kind: str | None = None) -> None:
        super().__init__(reason)
        self.kind = kind


def parse_reply(data: bytes) -> Reply:
    """Any reply a robot hears, checked; BadReply saying what is wrong."""
    try:
        message = parse_control(data)
    except ValueError as exc:
        raise BadReply(str(exc)) from None
    kind = REPLIES.get(message["type"])
    if kind is None:
        raise BadReply(f"unknown reply {message['type'][:40]!r}")
    try:
        return kind.parse(message)
    except ValueError as exc:
        raise BadReply(str(exc), kind.TYPE) from None

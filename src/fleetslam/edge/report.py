"""What a robot's run did (``fleetslam robot --report``, the run report's plots): its
counters, times and sends, filled in by the parts of the robot as they work."""

from __future__ import annotations

import json
import logging
from dataclasses import asdict, dataclass, field
from typing import Any

from fleetslam.transport.protocol import Welcome

log = logging.getLogger("fleetslam.robot")

# `fleetslam robot`'s exit status when the cloud kept less than the robot sent (a session
# it lost, frames lost on the link or with a worker): the report's `incomplete` says why.
EXIT_INCOMPLETE = 3


@dataclass
class RobotReport:
    robot_id: str
    offload_at: int
    frames: int = 0
    first_index: int = 0
    frames_lost_on_link: int = 0
    frame_bytes: int = 0
    control_bytes: int = 0
    keyframe_uploads: int = 0
    keyframe_bytes: int = 0
    upload_retries: int = 0
    # Uploads the cloud said it no longer needs (keyframes a restarted cloud lost).
    uploads_not_needed: int = 0
    # Frame indices of the keyframes the cloud acknowledged (stored and checkpointed).
    acknowledged: list[int] = field(default_factory=list)
    feedback: int = 0
    keyframes: int = 0
    robot_compute_s: float = 0.0
    robot_stage_ms: dict[str, float] = field(default_factory=dict)
    link_busy_s: float = 0.0
    round_trip_ms_median: float | None = None
    round_trip_ms_p95: float | None = None
    streaming_s: float = 0.0  # first frame sent -> last frame sent
    last_feedback_s: float = 0.0  # first frame sent -> last feedback received
    total_s: float = 0.0  # first frame sent -> the cloud's "ended" (map built)
    resumed_at: int | None = None
    # The cloud could not restore this robot's stored session (why, and where it kept the
    # checkpoint): the run started a fresh session, the history before it is not in it.
    history_lost: str | None = None
    # What the cloud kept: the frames its trajectory holds at the end (its summary's), and
    # why that is less than the robot sent (a session lost mid-run, frames lost on the
    # link or with a worker); empty: the cloud has every frame. `fleetslam robot` exits 3.
    cloud_frames: int | None = None
    incomplete: list[str] = field(default_factory=list)
    cloud_summary: dict[str, Any] | None = None
    # An adaptive robot: every re-plan (measured link, chosen point / features / step) and
    # how many frames went at each point; frames it skipped by its frame step (its own
    # choice, unlike camera_skipped).
    plan_history: list[dict[str, Any]] = field(default_factory=list)
    frames_per_point: dict[str, int] = field(default_factory=dict)
    frames_skipped: int = 0
    # A live source (None: a recording): what it is; the frames it delivered, those the
    # robot took from it, the
    # frames the camera delivered while the robot was busy and that a newer frame replaced
    # (the robot did not keep up with the camera), and on a resumed session the frames not
    # after the session's last timestamp (it has them already).
    live_source: str | None = None
    camera_delivered: int = 0
    camera_undelivered: int = 0  # produced by the camera, never delivered (a replay's late)
    camera_taken: int = 0
    camera_skipped: int = 0
    # Of those, the frames the camera delivered before the robot took its first (while it
    # connected and said hello): the start's, not the pace's.
    camera_skipped_at_start: int = 0
    camera_before_resume: int = 0
    # Messages of the camera the robot could not make a frame of (skipped and counted), and
    # why the camera's stream ended before the robot was stopped (a silent camera).
    camera_rejected: int = 0
    camera_ended: str | None = None
    # Keyframes the cloud asked for that the robot could no longer upload (a live camera's,
    # gone from its buffer, or from before a restart): the map is built without them.
    keyframes_unavailable: int = 0
    # Flow control: seconds the robot waited for its window of frames in flight, and the
    # waits that ran out (the cloud did not answer in time).
    flow_wait_s: float = 0.0
    flow_timeouts: int = 0
    # Times a cloud worker took the session over from its checkpoint (failover), and the
    # longest time between two feedbacks (the pause a takeover costs, or a backlog's).
    takeovers: int = 0
    longest_feedback_gap_s: float = 0.0
    # Every frame and keyframe upload put on the link, for the run report's plots of bytes
    # and link use over time: [start s, end s, bytes, "frame" | "keyframe", delivered], the
    # times since the first frame was read (start: handed to the link, which may first
    # finish earlier messages; end: its last bit sent). Recorded only, never sent.
    sends: list[tuple[float, float, int, str, bool]] = field(default_factory=list)
    # Message encoding per frame (inter-frame coding matches descriptors: robot CPU), and
    # the inter-frame coding's counts (wire/inter.py: intra share, descriptors coded inter).
    # Where the cloud placed this robot's map (``placed``): the group, T_global_map (4 x 4
    # rows) and whether a merge's outputs gave it (final); None: never joined.
    placed: dict[str, Any] | None = None
    placed_messages: int = 0
    placed_rejected: int = 0
    # Live ROS 2 out (``--ros2-out``): poses published, messages that found no router.
    ros2_poses: int = 0
    ros2_unpublished: int = 0
    # Per published pose: [frame index, taken, sent, feedback heard, put] in time.time_ns()
    # (a subscriber on this machine has the same clock; bench/ros2_out.py), the newest 20000.
    ros2_timings: list[tuple[int, int | None, int | None, int, int]] = \
        field(default_factory=list)
    encode_ms_mean: float | None = None
    encode_ms_p95: float | None = None
    # CPU time of the robot's own work on each frame sent (its stages and the message's
    # encoding, the main thread's: time.thread_time), ms, in order; wall times above count
    # the moments a shared or throttled CPU ran something else. And the whole process's CPU
    # seconds while it streamed (reading images, the link, uploads too).
    frame_cpu_ms: list[float] = field(default_factory=list)
    streaming_cpu_s: float = 0.0
    inter_coding: dict[str, Any] = field(default_factory=dict)

    def note_welcome(self, welcome: Welcome, at_frame: int | None) -> None:
        """A welcome to a hello: the robot's first (``at_frame`` None) or one mid-run, after
        the cloud lost the robot; a session the cloud could not keep is said and recorded."""
        lost = welcome.history_lost
        if lost:
            # The cloud could not restore this robot's stored session: it starts afresh.
            log.error("robot %s: the cloud lost this robot's session history and starts a "
                      "fresh session: %s", self.robot_id, lost)
            self.history_lost = str(lost)
            self.incomplete.append(f"the cloud lost the session's history: {lost}")
        if at_frame is None:
            return
        next_index = welcome.next_index
        if not welcome.resumed and not lost:
            why = f"the cloud no longer had this robot's session at frame {at_frame}: a " \
                  f"fresh session holds the frames from there on, not those before"
        elif next_index < at_frame:
            why = f"the cloud's session resumed at frame {next_index}: frames " \
                  f"{next_index}-{at_frame - 1}, sent before, are not in it"
        else:
            return
        log.error("robot %s: %s", self.robot_id, why)
        self.incomplete.append(why)

    def note_cloud_kept(self) -> None:
        """The end's summary: how many frames the cloud's trajectory holds against those
        sent; fewer is said and recorded."""
        frames = (self.cloud_summary or {}).get("frames")
        if not isinstance(frames, int):
            return
        self.cloud_frames = frames
        sent = self.first_index + self.frames
        # Frames the link lost are said already (its count); the others are news.
        if frames < sent - self.frames_lost_on_link:
            why = f"the cloud's trajectory holds {frames} of the {sent} frames sent " \
                  f"({self.frames_lost_on_link} of them lost on the link)"
            log.error("robot %s: %s", self.robot_id, why)
            self.incomplete.append(why)

    def summary_line(self) -> str:
        """What ``fleetslam robot`` says when it is done."""
        live = self.live_source is not None
        return (f"robot {self.robot_id}: {self.frames} frames sent from {self.first_index} "
                f"({self.frames_lost_on_link} lost on the link), {self.keyframes} keyframes "
                f"({self.upload_retries} upload retries), "
                f"{self.frame_bytes / max(self.frames, 1) / 1000:.1f} kB/frame, total "
                f"{self.total_s:.1f} s"
                + (f"; from {self.live_source}: {self.camera_taken} frames taken, "
                   f"{self.camera_skipped} skipped (the robot was busy), "
                   f"{self.camera_undelivered} never delivered by the camera, "
                   f"{self.camera_rejected} messages refused" if live else "")
                + (f"; the camera's stream ended: {self.camera_ended}" if self.camera_ended
                   else "")
                + (f"; the cloud kept {self.cloud_frames}" if self.cloud_frames is not None
                   else ""))

    def to_json(self) -> str:
        return json.dumps(asdict(self), indent=2)

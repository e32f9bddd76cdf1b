"""The robot process: read frames, run the stages before the offloading point, send the
state over the (emulated) link, follow the cloud's feedback, upload keyframes reliably.

``Robot`` composes parts with one job each and keeps the per-frame loop (``_stream``) and
the conversation with the cloud (hello / welcome, replies, end). Its threads:
- main thread: frames from the read-ahead thread, held back by ``pacing.Pacer`` (``--rate``)
  and by ``flow.FlowWindow`` (at most ``transport.max_frames_in_flight`` frames without
  feedback), through the stages and the wire encoding (``encoder.FrameEncoder``), handed to
  the send thread; from a live source (``datasets.live.LiveSource``: the camera is the
  clock) the newest frame each time it is ready for one, never paced, those it missed
  counted (``RobotReport.camera_skipped``);
- read thread (``pacing.read_ahead``): decodes the next images, as a camera driver would
  (a live source has its own camera thread instead);
- send thread (``sender.FrameOutbox``): frames onto the link, which blocks at link speed;
- uploader thread (``uploader.KeyframeUploader``): each keyframe's decimated RGB-D, resent
  until the cloud acknowledges it;
- Zenoh callbacks: feedback (pose, keyframe yes/no: the window, the encoder's references,
  the uploader, ROS 2 out) and replies by type (welcome, held, ack, need, ending, ended,
  placed) and, for errors, by ``protocol.Code`` (not_a_keyframe, reference_missing,
  no_session: hello again);
- with ``[ros2_out] endpoint`` (``--ros2-out``), ``ros2_out.RobotRosOut``'s threads: the
  connection to the robot's ROS 2 router, the path and the status at a low rate.
Frames, uploads and control messages share the one link (``sender.Sender``), so a robot
never sends faster than its link; each part counts what it did in the ``RobotReport``.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from fleetslam.config import Config
from fleetslam.datasets.live import LiveSource
from fleetslam.datasets.source import Frame, RecordedSource
from fleetslam.edge.cloud_replies import CloudRefused, CloudReplies
from fleetslam.edge.encoder import FrameEncoder, prepare
from fleetslam.edge.flow import FlowWindow
from fleetslam.edge.pacing import Pacer, live_frames, parse_rate, read_ahead
from fleetslam.edge.report import RobotReport
from fleetslam.edge.fleet_frame import FleetFrame
from fleetslam.edge.ros2_out import RobotRosOut
from fleetslam.edge.sender import FrameOutbox, Sender
from fleetslam.edge.uploader import KeyframeUploader
from fleetslam.pipeline.front_end import FrontEndState, front_end_stages
from fleetslam.pipeline.split import ROBOT_TRACKS, Sides, Stage, check_point
from fleetslam.planner.online import OnlinePlanner
from fleetslam.progress import Progress
from fleetslam.transport import keys, protocol
from fleetslam.transport.link import EmulatedLink
from fleetslam.transport.protocol import Hello
from fleetslam.transport.reachability import no_answer
from fleetslam.transport.zenoh_session import open_connecting, put
from fleetslam.wire.envelope import WireError
from fleetslam.wire.messages import decode_feedback

__all__ = ["END_TIMEOUT_S", "OnboardTracker", "Robot", "RobotReport", "parse_rate"]

log = logging.getLogger("fleetslam.robot")

# A robot that sends "end" waits this long for its last frames and map (cloud backlog).
END_TIMEOUT_S = 900.0


class OnboardTracker(Protocol):
    """The whole pipeline on the robot, for a robot that tracks by itself (point 6): the
    back-end needs the cloud's libraries, so whoever starts such a robot builds it
    (``fleetslam.backend.robot_slam.RobotSlam``)."""

    stages: list[Stage]
    sides: Sides

    def keyframe_poses(self) -> dict[int, np.ndarray]: ...


def _check_arguments(robot_id: str, live: LiveSource | None, offload_at: int, rate: str,
                     paper_yaml_dir: Path | None, planner: OnlinePlanner | None,
                     onboard: OnboardTracker | None) -> float | None:
    """The robot's frame rate (None: as fast as it goes); ValueError for arguments that do
    not go together."""
    check_point(offload_at)
    if (offload_at == ROBOT_TRACKS) != (onboard is not None):
        raise ValueError(f"a robot tracks by itself (and is given its onboard pipeline) at "
                         f"point {ROBOT_TRACKS} only, not at {offload_at}")
    fps = parse_rate(rate)
    if live is not None and fps is not None:
        raise ValueError(f"robot {robot_id}: {live.description} delivers frames at "
                         f"its own rate; --rate {rate} holds back recorded frames only")
    if paper_yaml_dir is not None and offload_at != 3:
        raise ValueError("the paper's YAML message holds the state at point 3 "
                         f"(--offload-at paper), not {offload_at}")
    if planner is not None and offload_at not in planner.cfg.online_points:
        raise ValueError(f"an adaptive robot starts at one of "
                         f"{', '.join(map(str, planner.cfg.online_points))}")
    return fps


class Robot:
    """``sequence``: a recording (paced by ``rate``) or a live source, started by the caller
    (its camera model builds the stages), which the robot closes when its run ends."""

    def __init__(self, robot_id: str, sequence: RecordedSource | LiveSource, source: str,
                 offload_at: int, config: Config, endpoint: str | None = None, rate: str = "max",
                 show_progress: bool = True, paper_yaml_dir: Path | None = None,
                 planner: OnlinePlanner | None = None,
                 link_trace: list[tuple[int, float]] | None = None,
                 onboard: OnboardTracker | None = None, localise_only: bool = False) -> None:
        self.robot_id = keys.check_robot_id(robot_id)
        self.live = sequence if isinstance(sequence, LiveSource) else None
        self.fps = _check_arguments(robot_id, self.live, offload_at, rate, paper_yaml_dir,
                                    planner, onboard)
        if paper_yaml_dir is not None:
            paper_yaml_dir.mkdir(parents=True, exist_ok=True)
        self.sequence = sequence
        self.source = source
        self.offload_at = offload_at
        # Its hello asks to be placed in the cloud's loaded map, never moving nor extending it.
        self.localise_only = localise_only
        self.config = config
        self.endpoint = endpoint or config.transport.endpoint
        self.show_progress = show_progress
        # An adaptive robot re-plans its point (among those the cloud switches between frame
        # by frame), its ORB features and its frame step while it runs.
        self.planner = planner
        self.link_trace = dict(link_trace or [])
        # The robot holds the state of the stages it runs: the front end at points 1-3 (an
        # adaptive robot may run any part of it at any moment), nothing at point 0 (the
        # cloud runs the front end), everything at point 6.
        self.onboard = onboard
        if onboard is not None:
            stages, sides = onboard.stages, onboard.sides
        else:
            runs_front_end = offload_at > 0 or planner is not None
            stages = front_end_stages()
            sides = Sides(edge=FrontEndState(config, sequence.camera) if runs_front_end else None)
        sequence.camera.mounted(config.camera.base_link)  # a bad mounting is said now
        # Once a process (warm_up is cached: `fleetslam robot` paid it before its camera).
        prepare(config, None if planner is not None else offload_at)
        self.report = RobotReport(robot_id, offload_at)
        self.encoder = FrameEncoder(self.robot_id, sequence.camera, config, stages, sides,
                                    self.report, paper_yaml_dir)
        self.window = FlowWindow(self.robot_id, config, self.report)
        if self.live is not None:
            self.report.live_source = self.live.description
        # A live camera keeps no recording to read an old keyframe from again.
        self.uploader = KeyframeUploader(self.robot_id, None if self.live else sequence,
                                         offload_at, config, self.report)
        # The robot's own ROS 2 graph: its pose, TF, path and status as they come.
        self.ros_out = RobotRosOut(self.robot_id, config.ros2_out, self.report, sequence) \
            if config.ros2_out.endpoint else None
        # Where the cloud places its map, and the node held up for it after the session.
        self.fleet_frame = FleetFrame(self.robot_id, self.report, self.ros_out,
                                      config.ros2_out.hold_s)
        self.sender: Sender | None = None  # the link, once run() has connected
        # What the cloud says: handled as it comes, or awaited by the run.
        self.replies = CloudReplies(self.robot_id, self.encoder, self.window, self.uploader,
                                    self.fleet_frame, self.report)
        self._resume_after: float | None = None  # a resumed live camera: the session's last stamp
        # Set by ``stop`` (the first Ctrl-C): the stream ends before its next frame and the
        # robot finishes with the cloud as at the end of a recording.
        self._stopping = threading.Event()

    # -- what the cloud says (Zenoh callbacks) --------------------------------------------

    def _on_feedback(self, sample: Any) -> None:
        self.take_feedback(sample.payload.to_bytes())

    def take_feedback(self, data: bytes) -> None:
        """The cloud's feedback on a frame (the Zenoh callback's): its place in flight
        freed, its pose to ROS 2, a keyframe's upload queued."""
        try:
            header, fb = decode_feedback(data)
        except WireError as exc:
            log.warning("robot %s: feedback rejected: %s", self.robot_id, exc)
            return
        now = self.window.heard()
        self.report.feedback += 1
        self.encoder.held(header.seq)  # as "held", for a cloud that does not send it
        self.encoder.tracked(header.seq)
        round_trip = self.window.answered(header.seq, now)
        if round_trip is not None and self.planner is not None:
            self.planner.meter.round_trip(round_trip)
        if self.ros_out is not None:
            self.ros_out.feedback(fb, round_trip)
        if fb.is_keyframe:
            self.report.keyframes += 1
            self.uploader.keyframe(fb.frame_index)

    def _on_reply(self, sample: Any) -> None:
        self.replies.take(sample.payload.to_bytes())

    # -- the run --------------------------------------------------------------------------

    def run(self) -> RobotReport:
        zs = open_connecting(self.endpoint, self.config.transport.reach_deadline_s,
                             self.config.transport.zenoh_config or None)
        self.sender = Sender(self.robot_id,
                             EmulatedLink(self.config.link, lambda key, data: put(zs, key, data)),
                             self.report, self.planner)
        subs = [zs.declare_subscriber(keys.feedback(self.robot_id), self._on_feedback),
                zs.declare_subscriber(keys.reply(self.robot_id), self._on_reply)]
        self.uploader.start(self.sender.send)
        if self.ros_out is not None:
            self.ros_out.start()
        try:
            self.end_session(self._stream())
            self.fleet_frame.hold()
        finally:
            if self.live is not None:
                self.live.close()
            if self.ros_out is not None:
                self.ros_out.close()
            self.uploader.stop()
            self.sender.close()
            for sub in subs:
                sub.undeclare()
            zs.close()
        return self.report

    def stop(self) -> None:
        """End the stream before the next frame; the run then ends as at the end of a
        recording (the end message, the uploads the cloud still needs, its 'ended'): how a
        live camera's run is ended."""
        self._stopping.set()
        self.fleet_frame.release()

    def _stream(self) -> int:
        """The robot's per-frame loop: adapt, pace, wait for room, encode, keep, send; the
        last frame's seq."""
        seq, start_index = self._open_session()
        n = None if self.live is not None else len(self.sequence)
        progress = Progress(f"robot {self.robot_id} (offload at {self.offload_at})",
                            None if n is None else n - start_index, enabled=self.show_progress)
        t0 = self.sender.t0 = time.monotonic()
        cpu0 = time.process_time()
        pacer = Pacer(self.fps, t0, start_index)
        outbox = FrameOutbox(self.sender, self.window)
        k, step = self.offload_at, 1
        i = start_index - 1
        for i, frame in enumerate(self._frames(start_index), start_index):
            if self._stopping.is_set():
                break
            if i == start_index and self.live is not None:
                self.report.camera_skipped_at_start = self.live.skipped
            k, step = self._adapt(i, start_index, k, step)
            if step > 1 and (i - start_index) % step and i != (n or 0) - 1:
                self.report.frames_skipped += 1
                continue
            if self.replies.need_hello.is_set():  # the cloud lost us (no checkpoint)
                outbox.drain()
                welcome = self._hello()
                self.report.note_welcome(welcome, i)
                seq = max(seq, welcome.next_seq)
            pacer.wait(i, frame.timestamp)
            if not self.window.wait_for_room():
                # Nobody may be serving this robot any more (a cloud that lost it, a worker
                # gone): a hello is heard by every worker and gets it served again.
                self.replies.need_hello.set()
            if self.ros_out is not None:
                self.ros_out.taken(frame.index)
            data = self.encoder.encode(frame, k, seq)
            self.uploader.keep(frame, k)
            self.report.frames_per_point[str(k)] = self.report.frames_per_point.get(str(k), 0) + 1
            self.window.sent(seq)
            if self.ros_out is not None:
                self.ros_out.sent(frame.index)
            outbox.put(seq, data)
            self.report.frames += 1
            self.report.frame_bytes += len(data)
            seq += 1
            progress.update(i + 1 - start_index, self._progress_note(k, step))
        outbox.close()
        if self.live is not None:  # whether the camera's stream ended or the robot stopped
            self.report.camera_skipped = self.live.skipped
            self.report.camera_delivered = self.live.delivered
            self.report.camera_undelivered = self.live.undelivered
            self.report.camera_rejected = self.live.rejected
        progress.finish(i + 1 - start_index, self._progress_note(k, step))
        self.report.streaming_s = time.monotonic() - t0
        self.report.streaming_cpu_s = time.process_time() - cpu0
        return seq - 1

    def _progress_note(self, k: int, step: int) -> str:
        return (f"kf {self.report.keyframes}"
                + (f" camera skipped {self.live.skipped}" if self.live is not None else "")
                + (f" k={k} f={self.encoder.features} step={step}"
                   if self.planner is not None else ""))

    def _frames(self, start_index: int) -> Iterator[Frame]:
        """A recording's frames from ``start_index`` on (read ahead), or the live camera's
        newest frame each time the loop asks, numbered on from ``start_index``."""
        if self.live is None:
            yield from read_ahead(self.sequence, start_index, f"robot-{self.robot_id}-read")
            return
        yield from live_frames(self.live, start_index, self.config.source.live_frame_timeout_s,
                               self._stopping, self.report, self._resume_after, self.robot_id)

    def _adapt(self, i: int, start_index: int, k: int, step: int) -> tuple[int, int]:
        """Before frame ``i``: the emulated link changes (a recorded trace); an adaptive robot
        re-plans its point, features and frame step every ``planner.replan_frames`` frames."""
        if i in self.link_trace:
            self.sender.link.set_bandwidth(self.link_trace[i])
        if self.planner is not None and i > start_index \
                and (i - start_index) % self.planner.cfg.replan_frames == 0:
            setting = self.planner.replan(i)
            self.encoder.use_features(setting.features)
            return setting.k, setting.frame_step
        return k, step

    def _open_session(self) -> tuple[int, int]:
        """Hello: the session's next seq and the frame it starts (or resumes) at."""
        welcome = self._hello()
        start_index = welcome.next_index
        # A live camera cannot go back to a frame index: it numbers its frames on from the
        # session's next index, and drops those not after the session's last timestamp (a
        # replay restarted from its beginning; a camera's clock has moved on anyway).
        self._resume_after = welcome.last_timestamp if self.live is not None else None
        if welcome.resumed and start_index and self.offload_at == ROBOT_TRACKS:
            raise RuntimeError(
                f"robot {self.robot_id}: the cloud has {start_index} frames of this session, "
                f"but a robot that tracks itself (point 6) kept its map on the robot and "
                f"cannot resume it; start again under a new --id")
        self.report.note_welcome(welcome, None)
        if welcome.resumed:
            self.report.resumed_at = start_index
            log.info("robot %s: resuming the cloud's session at frame %d", self.robot_id,
                     start_index)
        self.report.first_index = start_index
        return welcome.next_seq, start_index

    def _hello(self) -> protocol.Welcome:
        # A live camera's frame count is unknown (None) until it stops; the cloud reads it
        # nowhere (resume goes by its own next index).
        # The cloud hears the camera's mounting too (the fleet's map frame: map_frame.py).
        camera = self.sequence.camera.mounted(self.config.camera.base_link)
        message = Hello(self.offload_at, camera, self.source, self.planner is not None,
                        self.localise_only).message(
            None if self.live is not None else len(self.sequence))
        cfg = self.config.transport
        full = 0  # refusals because the cloud was full
        waiting = None  # why the cloud said it cannot serve yet, the last time
        hint_at = time.monotonic() + cfg.silence_hint_s
        for _ in range(cfg.max_attempts):
            if time.monotonic() >= hint_at:  # once: the session is open, the cloud silent
                hint_at = math.inf
                log.warning("robot %s: no answer to its hello from the cloud at %s yet: %s; "
                            "saying hello %d times in all", self.robot_id, self.endpoint,
                            self._silence(), cfg.max_attempts)
            self.sender.control(message)
            try:
                welcome = self.replies.await_reply((protocol.Welcome,), cfg.connect_timeout_s,
                                                   "hello")
            except CloudRefused as refusal:
                if refusal.wait:  # e.g. its coordination service out of reach: hello again
                    if waiting != refusal.reason:
                        log.warning("robot %s: %s; saying hello again", self.robot_id,
                                    refusal.reason)
                    waiting = refusal.reason
                    hint_at = math.inf  # it answers: not silence
                    time.sleep(cfg.connect_timeout_s)
                    continue
                # A full cloud frees slots (robots end, empty sessions expire): a few more
                # hellos, further apart. Any other refusal (a bad hello, a changed point)
                # would be refused again: stop at once.
                if refusal.code == protocol.Code.SESSION_ENDED.value:
                    raise  # its reason says what to do (a new --id)
                if not refusal.full:
                    raise RuntimeError(f"robot {self.robot_id}: the cloud at {self.endpoint} "
                                       f"refused it: {refusal.reason}") from None
                if full >= cfg.full_retries:
                    raise RuntimeError(f"robot {self.robot_id}: the cloud at {self.endpoint} "
                                       f"is full ({refusal.max_sessions} sessions), refused "
                                       f"{full + 1} times: {refusal.reason}") from None
                wait = cfg.full_retry_s * 2 ** full
                full += 1
                hint_at = math.inf  # it answers: not silence
                log.warning("robot %s: the cloud at %s is full (%s sessions); hello again "
                            "in %.0f s", self.robot_id, self.endpoint, refusal.max_sessions,
                            wait)
                time.sleep(wait)
                continue
            if welcome is not None:
                self.replies.need_hello.clear()
                self.encoder.restart(welcome)
                self.window.clear()  # a new or resumed session answers none of them
                return welcome
        raise RuntimeError(f"robot {self.robot_id}: no session from the cloud at "
                           f"{self.endpoint} after {cfg.max_attempts} hellos: "
                           f"{waiting or self._silence()}")

    def _silence(self) -> str:
        """What to check when the cloud does not answer this robot's open session."""
        return no_answer(self.endpoint, self.config.transport.zenoh_config or None,
                         self.robot_id)

    def end_session(self, last_seq: int) -> None:
        """Tell the cloud the stream ended at ``last_seq``; upload whatever keyframes it
        still needs; wait for its 'ended' (trajectory and map written)."""
        self.uploader.wait()
        poses = self.onboard.keyframe_poses() if self.onboard is not None else {}
        camera = None if self.live is None else {
            "source": self.live.description, "delivered": self.report.camera_delivered,
            "undelivered": self.report.camera_undelivered,
            "taken": self.report.camera_taken, "skipped": self.report.camera_skipped}
        cfg = self.config.transport
        for _ in range(cfg.max_attempts):
            if self.uploader.error:
                raise RuntimeError(self.uploader.error)
            if self.replies.need_hello.is_set():  # the cloud lost the session meanwhile
                self._hello_while_ending()
            # Keyframes the robot cannot upload (a live camera's, gone from its buffer): the
            # cloud builds the map without their images instead of asking again.
            self.sender.control(protocol.End(last_seq, poses, camera,
                                             frozenset(self.uploader.unavailable)))
            if self.replies.await_reply((protocol.Ending,), cfg.connect_timeout_s) is None:
                continue  # the end message was lost, or the cloud is restarting
            try:
                answer = self.replies.await_reply((protocol.Need, protocol.Ended), END_TIMEOUT_S,
                                          "end")
            except CloudRefused as refusal:
                if refusal.code != protocol.Code.FAILED.value:
                    raise RuntimeError(f"robot {self.robot_id}: the cloud at {self.endpoint} "
                                       f"refused its end: {refusal.reason}") from None
                # Not ended (its final checkpoint is not durable): end again, soon.
                log.warning("robot %s: the cloud did not end the session: %s",
                            self.robot_id, refusal.reason)
                time.sleep(cfg.connect_timeout_s)
                continue
            if answer is None:
                raise RuntimeError(f"robot {self.robot_id}: the cloud did not finish in "
                                   f"{END_TIMEOUT_S:.0f} s")
            if isinstance(answer, protocol.Ended):
                self._record_end(answer)
                return
            log.info("robot %s: cloud needs keyframes %s", self.robot_id, list(answer.frames))
            for index in answer.frames:
                self.uploader.queue(index)
            self.uploader.wait()
        raise RuntimeError(f"robot {self.robot_id}: the cloud never confirmed the end")

    def _hello_while_ending(self) -> None:
        """Hello again while ending (the cloud lost the session meanwhile): a session that
        ended already (its "ended" was lost) is refused as ended, and the next end hears
        "ended" again."""
        try:
            welcome = self._hello()
        except CloudRefused as refusal:
            if refusal.code != protocol.Code.SESSION_ENDED.value:
                raise
            self.replies.need_hello.clear()
            return
        self.report.note_welcome(welcome, self.report.first_index + self.report.frames)

    def _record_end(self, answer: protocol.Ended) -> None:
        r = self.report
        r.total_s = time.monotonic() - self.sender.t0
        r.link_busy_s = self.sender.link.stats.busy_s
        self.window.record(r, self.sender.t0)
        self.encoder.record(r)
        r.cloud_summary = answer.summary
        r.note_cloud_kept()
        if self.planner is not None:
            r.plan_history = self.planner.history

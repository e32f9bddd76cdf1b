"""One robot's session in the cloud: the tracking of its frames (the stages after the
offloading point), its keyframe uploads and the control protocol with its robot. Sessions
share nothing, and each runs on threads of its own, so one robot's bad message or slow map
never touches another's. Zenoh's callbacks only enqueue (submit_*); then

- the receive thread decodes each frame as it comes and tells the robot it holds it as a
  reference (inter-frame coding), even while the tracker is busy;
- the tracking thread takes frames and control messages in arrival order;
- the keyframe thread stores keyframe uploads, acknowledged once a checkpoint covers them;
- the checkpoint writer (checkpoint_writer.py) writes the checkpoints taken at keyframes,
  at the end and on closing, then hands each new keyframe to the merger.

Its other parts: inbox.py (the inbox; admission: a flooding robot is paused), memory_budget.py
(the bytes it holds: beyond its budget, frames and uploads are dropped unread), session_outputs.py
(the robot's files and summary when it ends), session_state.py (what a checkpoint holds).
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections import Counter
from typing import Any, Callable

from fleetslam.backend.back_end import new_state
from fleetslam.backend.workers import LocalMappingPool
from fleetslam.cloud.session import frame_order, session_state
from fleetslam.cloud.session.checkpoint_writer import CheckpointWriter, KeyframeSink
from fleetslam.cloud.session.inbox import (IDLE, REJECTION_REPLY_INTERVAL_S, Admission,
                                           CallItem, ControlItem, FrameItem, Throttle,
                                           WorkQueue)
from fleetslam.cloud.session.end_handshake import EndHandshake
from fleetslam.cloud.session.keyframe_uploads import KeyframeUploads
from fleetslam.cloud.session.memory_budget import (MB, SessionBudget, captured_frame_bytes,
                                                   held_bytes)
from fleetslam.cloud.session.replies import Publish, Replies
from fleetslam.cloud.session.session_outputs import FinishedMap, SessionOutputs
from fleetslam.cloud.session.session_state import SessionState, TrajectoryRow
from fleetslam.cloud.session.session_tracker import session_tracker
from fleetslam.cloud.session.store import CloudStore
from fleetslam.config import Config
from fleetslam.pipeline.split import CLOUD_TRACKS
from fleetslam.pipeline.states import CapturedFrame, TrackedFrame
from fleetslam.transport import keys, protocol
from fleetslam.transport.protocol import Hello
from fleetslam.visualisation.live_view import NullView
from fleetslam.wire.data_tree import Capture
from fleetslam.wire.envelope import Header
from fleetslam.wire.frames import state_index_time
from fleetslam.wire.inter import ReferenceRing
from fleetslam.wire.messages import Feedback, encode_feedback

log = logging.getLogger("fleetslam.cloud")

# An end waiting for frames still in flight is looked at again this often.
END_RECHECK_S = 0.05

# Counts of what the memory budget dropped unread (always in the summary, 0 included).
OVER_BUDGET = {"frame": "frames dropped unread (over memory budget)",
               "keyframe": "keyframes dropped unread (over memory budget)"}



class RobotSession:
    def __init__(self, state: SessionState, config: Config, store: CloudStore,
                 publish: Publish, keyframe_sink: KeyframeSink | None = None,
                 view: NullView | None = None,
                 local_mapping: LocalMappingPool | None = None) -> None:
        self.state = state
        # The live view (off: a NullView); its calls only enqueue, never wait.
        self.view = view or NullView()
        self.config = config
        self.store = store
        # Who tracks the robot (this cloud, or the robot itself at point 6), and its
        # keyframes as the merger and the view take them.
        self.tracker = self.keyframes = session_tracker(state, config, local_mapping)
        self.outputs = SessionOutputs(state, config, store, self.tracker.slam,
                                      self.transport_counts)
        # Why the robot's earlier session could not be restored (None: nothing was lost).
        self.history_lost: str | None = None
        # Decoded frames that inter-coded frames refer to (not checkpointed: a restored
        # session refuses references to frames before it, and the robot sends intra).
        self.references = ReferenceRing(config.wire.reference_frames)
        counts_lock = threading.Lock()  # the frame and keyframe threads count, status reads
        self.admission = Admission(state.robot_id, config.transport, state.counts, counts_lock)
        # What it says to the robot (nothing more once dropped: another worker serves it).
        self.replies = Replies(state.robot_id, publish, self.admission, state.counts,
                               counts_lock)
        self.last_heard = self.opened = time.monotonic()
        # Whether a frame has arrived (a hello alone holds a slot only until it is needed).
        self.heard_frame = False
        # The bytes its frames, uploads and references hold (memory_budget.py); each frame
        # and upload releases its charge when handled or dropped.
        self.budget = SessionBudget(int(config.transport.session_budget_mb * MB),
                                    captured_frame_bytes(state.hello.camera))
        # Frames and control in arrival order: the receive thread decodes each frame (and
        # tells the robot it holds it as a reference) and passes it on to the tracking
        # thread, so a busy tracker does not delay what inter-frame coding may refer to.
        self._frames = WorkQueue(config.transport.max_queued_frames, self.budget)
        self._decoded = WorkQueue(config.transport.max_queued_frames, self.budget)
        self._keyframes: queue.Queue[FrameItem | None] = queue.Queue()
        # A failure's traceback is logged, and a robot over its budget told, at most once
        # per reason and interval (a robot repeating what fails must not fill the log).
        self._failure_log = Throttle(REJECTION_REPLY_INTERVAL_S)
        self._over_budget_told = Throttle(REJECTION_REPLY_INTERVAL_S)
        # The checkpoints' parts that never change are written once (session_state.Chunks).
        self.chunks = session_state.Chunks(*store.chunk_files(state.robot_id))
        self.checkpoints = CheckpointWriter(state.robot_id, store, self._snapshot,
                                            state.last_index, keyframe_sink,
                                            ended=lambda: self.state.ended,
                                            written=self.chunks.confirm,
                                            interval_s=config.transport.checkpoint_interval_s)
        self.ends = EndHandshake(state, config, store, self.tracker.slam, self.outputs,
                                 self.checkpoints, self.replies, self._frames)
        self.decoder = frame_order.FrameDecoder(state, self.references, self.replies,
                                                self.budget)
        self.uploads = KeyframeUploads(state, config, store, self.checkpoints, self.budget,
                                       self.replies, self.keyframes, self.view,
                                       self.outputs.clouds)
        self._threads = [threading.Thread(target=work, name=f"cloud-{state.robot_id}{name}",
                                          daemon=True)
                         for work, name in ((self._receive, "-receive"),
                                            (self._serve_tracking, ""),
                                            (self._serve_uploads, "-keyframes"))]

    @staticmethod
    def open(robot_id: str, hello: Hello, config: Config, store: CloudStore,
             publish: Publish, keyframe_sink: KeyframeSink | None = None,
             view: NullView | None = None,
             local_mapping: LocalMappingPool | None = None) -> "RobotSession":
        # The front end's state is made by the first frame that needs it (_track).
        return RobotSession(SessionState(robot_id, hello, new_state(config, hello.camera)),
                            config, store, publish, keyframe_sink, view, local_mapping).start()

    # -- lifecycle ------------------------------------------------------------------------

    def start(self) -> "RobotSession":
        """Start the session's threads; a session restored after its robot ended has its
        finished map for the merge (its outputs were written before that checkpoint)."""
        if self.state.ended and self.ends.finished is None:
            self.ends.finished = self.outputs.finished_map()
        for t in self._threads:
            t.start()
        self.checkpoints.start()
        return self

    def close(self, timeout: float = 5.0, final_checkpoint: bool = False) -> None:
        """Stop the session's threads once the work already queued is done; with
        ``final_checkpoint``, the state as it is then goes to disk first (an idle session
        is closed this way and restored from it when its robot speaks again)."""
        self._frames.put(None)
        self._keyframes.put(None)
        for t in self._threads:
            if t.is_alive():
                t.join(timeout)
        if final_checkpoint:
            self.checkpoints.checkpoint(self.state.last_index)
        elif not self.replies.dropped.is_set():
            self.checkpoints.capture()  # a keyframe's, waiting for its interval
        # Only now: the frame thread may still have queued a keyframe's checkpoint.
        self.checkpoints.close(timeout)
        self.tracker.slam.close()  # its worker's copy of its keyframe database goes

    def drop(self) -> None:
        """Stop at once saying anything to the robot (another worker serves it now), and
        close without a checkpoint (the store would refuse it) on a thread of its own: the
        caller may be the lease's, which must not wait for the work queued."""
        self.replies.dropped.set()
        threading.Thread(target=self.close, name=f"drop-{self.robot_id}", daemon=True).start()

    def drain(self, timeout: float = 60.0) -> None:
        """Wait until everything submitted so far is processed (tests, shutdown)."""
        done = threading.Event()
        self.run_in_order(done.set, before_decoding=True)
        done.wait(timeout)

    def run_in_order(self, call: Callable[[], object], before_decoding: bool = False) -> None:
        """Run ``call`` on the tracking thread after the frames submitted so far (and
        before later ones); ``before_decoding``: after the frames submitted so far are
        decoded, too (the receive thread waits for it)."""
        if before_decoding:
            self._frames.put(CallItem(call))
        else:
            self._decoded.put(CallItem(call))

    @property
    def robot_id(self) -> str:
        return self.state.robot_id

    # -- entry points (called from Zenoh callbacks: only enqueue) -----------------------

    def submit_frame(self, data: bytes, arrival: float) -> None:
        self.last_heard = time.monotonic()
        self.heard_frame = True
        self.view.received(self.robot_id, len(data))
        if self.admission.paused():
            return
        charge = self.budget.frame_charge(len(data))
        if self._admit("frame", charge):
            self._frames.put(FrameItem(data, arrival, charge))

    def submit_control(self, message: dict[str, Any], arrival: float) -> bool:
        """Whether the control message is taken (admission: not while paused, at most
        ``transport.max_control_per_s``); a refused one is counted and its reason told
        (throttled). An end while another waits replaces that one's content."""
        self.last_heard = time.monotonic()
        refused = self.admission.control_refused()
        if refused is not None:
            if refused != "paused":
                self.replies.reject("control", refused, protocol.Code.REFUSED)
            return False
        if message.get("type") == "end" and not self.ends.offer(message):
            return True
        self._frames.put(ControlItem(message, arrival))
        return True

    def reject_control(self, reason: str) -> None:
        """A control message that did not parse: counted against the robot like a bad frame
        (a flood of them pauses it), the reason told at most once per interval."""
        self.last_heard = time.monotonic()
        self.replies.reject("control", reason, protocol.Code.BAD_MESSAGE)

    def submit_keyframe(self, data: bytes, arrival: float) -> None:
        self.last_heard = time.monotonic()
        self.view.received(self.robot_id, len(data))
        if not self.admission.paused() and self._admit("keyframe", len(data)):
            self._keyframes.put(FrameItem(data, arrival, len(data)))

    def _admit(self, what: str, charge: int) -> bool:
        """Whether a message of ``charge`` bytes fits the session's budget; if not it is
        dropped unread (counted) and the robot told to slow down, at most once a second."""
        if self.budget.admit(charge):
            return True
        self.replies.count(OVER_BUDGET[what])
        if self._over_budget_told.due("over budget"):
            limit = self.config.transport.session_budget_mb
            self.replies.reply(protocol.Error.of(
                protocol.Code.OVER_BUDGET,
                f"{what} dropped unread: the session holds its memory budget of {limit:.0f} MB "
                f"(transport.session_budget_mb); keep to max_frames_in_flight"
                + (" and resend it once acknowledged ones leave room" if what == "keyframe"
                   else ""), rejected=what))
        return False

    # -- counts -------------------------------------------------------------------------

    def counts(self) -> Counter:
        return self.replies.counts()

    def queued_frames(self) -> list[FrameItem]:
        """The frames waiting in the session's inboxes (to decode, to track)."""
        return self._frames.waiting_frames() + self._decoded.waiting_frames()

    def transport_counts(self) -> dict[str, int]:
        """The counts as the summary's ``transport`` has them."""
        return {**{name: 0 for name in OVER_BUDGET.values()}, **self.counts(),
                "frames dropped (session busy)": self._frames.dropped + self._decoded.dropped,
                "memory budget peak bytes": self.budget.peak}

    def _snapshot(self) -> Capture:
        """The state as a checkpoint now; under the counts lock, since the keyframe thread
        counts while this copies."""
        with self.replies.counts_lock:
            return session_state.capture(self.state, self.chunks)

    # -- threads ------------------------------------------------------------------------

    def _serve_uploads(self) -> None:
        while (item := self._keyframes.get()) is not None:
            self._guarded("keyframe", self.uploads.take, item.data)

    def _serve_tracking(self) -> None:
        """Frames and control in order; an end waiting for frames in flight is looked at
        after each frame and every END_RECHECK_S, a keyframe's checkpoint waiting for its
        interval when it is due (this thread's own timers: no thread per end)."""
        while True:
            waits = [END_RECHECK_S if self.ends.held_for_frames else None,
                     self.checkpoints.due_in()]
            item = self._decoded.get(min((w for w in waits if w is not None), default=None))
            if item is None:
                return
            if isinstance(item, FrameItem):
                self._guarded("frame", self._track_frame, item)
            elif isinstance(item, ControlItem):
                self._guarded("control", self._on_control, item.message, item.arrival)
            elif isinstance(item, CallItem):
                self._guarded("call", item.call)
            if self.ends.held_for_frames and (item is IDLE or isinstance(item, FrameItem)):
                self._guarded("end again", self.ends.take, None, 0.0)
            self._guarded("checkpoint", self.checkpoints.capture_due)

    def _guarded(self, kind: str, work: Callable[..., object], *args: Any) -> None:
        try:
            work(*args)
        except Exception as exc:  # a bug on one message must not end the robot's session
            self._failed(kind, exc)

    def _failed(self, kind: str, exc: Exception) -> None:
        """Count a failure; its traceback goes to the log once per reason and interval."""
        self.replies.count("errors")
        if self._failure_log.due(f"{kind} {type(exc).__name__} {exc}"):
            log.error("robot %s: %s message failed (%d failures so far)", self.robot_id,
                      kind, self.counts()["errors"], exc_info=exc)

    def _receive(self) -> None:
        """Decode each frame as it arrives (the reference ring must hold it before a frame
        coded against it comes), say so to the robot, and hand everything on in order."""
        while True:
            item = self._frames.get()
            if isinstance(item, FrameItem):
                item = self._decoded_item(item)
                if item is None:
                    continue
            self._decoded.put(item)  # type: ignore[arg-type]
            if item is None:
                return

    def _decoded_item(self, item: FrameItem) -> FrameItem | None:
        """The frame decoded, charged at its arrays' size until tracked; None: rejected."""
        try:
            decoded = self.decoder.decode(item.data or b"")
        except Exception as exc:  # a bug on one message must not end the session
            decoded = None
            self._failed("frame", exc)
        if decoded is None:
            self.budget.release(item.charge)
            return None
        actual = held_bytes(decoded[1])
        self.budget.decoded(item.charge, actual)
        return FrameItem(None, item.arrival, actual, decoded)

    def _track_frame(self, item: FrameItem) -> None:
        try:
            self._on_frame(item.decoded, item.arrival)
        finally:
            self.budget.release(item.charge)

    # -- frames (the tracking thread; frame_order.py decodes them on arrival) -------------

    def _on_frame(self, decoded: tuple, arrival: float) -> None:
        """Track a decoded frame, record it, checkpoint at a keyframe, send the feedback."""
        st = self.state
        header, state = decoded
        switching = st.hello.adaptive and header.split_point in CLOUD_TRACKS
        if header.split_point != st.hello.offload_at and not switching:
            # No session at this point: the robot says hello again (on the code).
            return self.replies.reject(
                "frame", f"split point {header.split_point}, but the session offloads at "
                         f"{st.hello.offload_at} (send a hello)", protocol.Code.NO_SESSION)
        out_of_sequence = frame_order.out_of_sequence(st, header, state_index_time(state)[0])
        if out_of_sequence is not None:
            return self.replies.reject("frame", out_of_sequence)
        refusal = self.tracker.refusal(state)
        if refusal is not None:
            return self.replies.reject("frame", refusal)
        missing = self.tracker.poses_missing(state)
        if missing is not None:  # the robot sends its keyframe poses whole from now on
            return self.replies.reject("frame", missing, protocol.Code.REFERENCE_MISSING)
        if st.last_seq >= 0 and header.seq > st.last_seq + 1:
            self.replies.count("frames lost in transit", header.seq - st.last_seq - 1)
        start = time.perf_counter()
        out, to_merger = self.tracker.track(state, header.split_point, header.seq)
        cloud_ms = 1000.0 * (time.perf_counter() - start)
        self._record(header, out, cloud_ms)
        if out.is_keyframe:
            self._on_new_keyframe(state, header.seq, out.index, to_merger)
        elif self.checkpoints.older_than(self.config.transport.checkpoint_every_s):
            self.checkpoints.checkpoint(out.index, now=False)
        feedback = Feedback(out.index, out.timestamp, out.tracked, out.is_keyframe,
                            out.n_inliers, out.T_world_camera, cloud_ms)
        self.replies.publish(keys.feedback(self.robot_id),
                             encode_feedback(self.robot_id, header.seq, feedback))
        st.latency_ms.append(1000.0 * (time.monotonic() - arrival))

    def _record(self, header: Header, out: TrackedFrame, cloud_ms: float) -> None:
        """The tracked frame in the trajectory, the counts and the live view."""
        st = self.state
        st.last_seq = header.seq
        st.last_index = out.index
        self.replies.count("frames")
        st.rows.append(TrajectoryRow(out.index, out.timestamp, out.T_world_camera.copy(),
                                     out.tracked, out.is_keyframe, out.reference_keyframe,
                                     out.T_reference_camera))
        st.cloud_ms.append(cloud_ms)
        now = time.monotonic()
        st.first_frame_time = st.first_frame_time or now
        st.last_frame_time = now
        self.view.frame(self.robot_id, out.index, st.rows[-1].T_world_camera, out.tracked,
                        out.is_keyframe, header.split_point, cloud_ms, out.timestamp)

    def _on_new_keyframe(self, state: Any, seq: int, frame_index: int,
                         to_merger: bool) -> None:
        """The frame became a keyframe: its RGB-D to the store if the cloud has it, and a
        checkpoint of the session as it is now (the snapshot here, the slow durable write on
        the writer thread). The keyframe's upload is acknowledged, and the keyframe handed to
        the merger (``to_merger``: it has features, which a robot that tracks itself sends
        with each keyframe), only once this checkpoint is on disk, so no acknowledged or
        merged keyframe is one a restart or a takeover forgets."""
        if isinstance(state, CapturedFrame):
            # Total offloading: the cloud already has the keyframe's RGB-D.
            self.uploads.store_captured(state, seq)
        self.checkpoints.checkpoint(frame_index, self.keyframes.newest() if to_merger else None,
                                    now=False)
        moved = self.tracker.moved_keyframes() if self.view.enabled else None
        if moved is not None:
            self.view.keyframe_poses(self.robot_id, *moved)

    # -- control (the tracking thread, in order with the frames) --------------------------

    def welcome(self, resumed: bool, taken_over: bool = False) -> None:
        st = self.state
        self.replies.reply(protocol.Welcome(resumed, st.last_index + 1, st.last_seq + 1,
                                            len(self.store.keyframe_indices(self.robot_id)),
                                            self.references.size, taken_over,
                                            st.rows[-1].timestamp if st.rows else None,
                                            self.history_lost, pose_deltas=True))

    def _on_control(self, message: dict[str, Any], arrival: float) -> None:
        kind = message.get("type")
        if kind == "hello":
            if self.finished is not None:
                return self._refuse_ended()
            self.welcome(resumed=True)
        elif kind == "end":
            self.ends.take(message, arrival)
        else:
            self.replies.reject("control", f"unknown control message {str(kind)[:40]!r}",
                                protocol.Code.UNKNOWN_TYPE)

    def _refuse_ended(self) -> None:
        """A hello for this ended session: a new run of the robot, refused with why (or the
        robot ending it, which then ends again and hears "ended")."""
        st = self.state
        self.replies.reply(protocol.Error.of(
            protocol.Code.SESSION_ENDED,
            f"robot {self.robot_id}'s session ended at frame {st.last_index} "
            f"({len(st.rows)} frames tracked); its trajectory and map stay as written in the "
            f"store's {self.robot_id}/, and a finished session is never resumed: run the "
            f"robot under a new --id", answer_to="hello"))

    @property
    def finished(self) -> FinishedMap | None:
        """The robot's finished map once its end is durable (None: not ended)."""
        return self.ends.finished

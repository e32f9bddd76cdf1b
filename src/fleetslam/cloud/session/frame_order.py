"""A robot's frames as its session takes them: decoded as they arrive (the receive thread:
an inter-coded frame may refer to any frame before it, so the reference ring must hold each
one at once, even while the tracker is busy), then checked to follow the tracked ones (the
tracking thread: seq, frame index and stamp against the trajectory)."""

from __future__ import annotations

from typing import Any

from fleetslam.cloud.session.memory_budget import SessionBudget
from fleetslam.cloud.session.replies import Replies
from fleetslam.cloud.session.session_state import SessionState
from fleetslam.transport import protocol
from fleetslam.wire.envelope import Header, WireError
from fleetslam.wire.frames import decode_frame_message
from fleetslam.wire.inter import MissingReference, ReferenceRing, reference_of

# A robot's seq may skip frames lost on the link, but not this many at once.
MAX_SEQ_JUMP = 100_000
# A frame index jumps at most this far too (a robot's frame step, frames skipped by a live
# camera): a forged far-future index would make every later real frame "out of order".
MAX_INDEX_JUMP = 100_000


class FrameDecoder:
    """Frames decoded on arrival; each one inter-coded frames may refer to is held in the
    ring (charged to the session's budget) and the robot told so."""

    def __init__(self, state: SessionState, references: ReferenceRing, replies: Replies,
                 budget: SessionBudget) -> None:
        self.state, self.references, self.replies, self.budget = \
            state, references, replies, budget
        self._newest_seq = state.last_seq  # newest frame put in the reference ring

    def decode(self, data: bytes) -> tuple[Header, Any] | None:
        """(header, state), or None if rejected (the robot told why)."""
        robot_id = self.state.robot_id
        try:
            header, state = decode_frame_message(data, self.state.hello.camera, self.references)
        except MissingReference as exc:
            return self.replies.reject("frame", str(exc), protocol.Code.REFERENCE_MISSING,
                                       seq=exc.seq, missing=exc.missing)
        except WireError as exc:
            return self.replies.reject("frame", str(exc))
        if header.robot_id != robot_id:
            return self.replies.reject("frame", f"header names robot {header.robot_id!r}, "
                                                f"sent on {robot_id!r}'s key")
        reference = reference_of(state)
        # Only ever newer seqs: a replayed or reordered message must not replace what a
        # later frame was coded against.
        if 0 < header.seq - self._newest_seq <= MAX_SEQ_JUMP:
            self._newest_seq = header.seq
            if reference is not None and self.references.size:
                self.references.put(header.seq, reference)
                self.budget.references(self.references.nbytes())
                self.replies.reply(protocol.Held(header.seq))
        return header, state


def out_of_sequence(st: SessionState, header: Header, index: int) -> str | None:
    """Why a frame does not follow the tracked ones (seq, frame index, timestamp), or None.
    The index is the trajectory's row and a keyframe's name (uploads, the merge): at point 6
    the robot's own, recorded as sent, so it is checked like the seq."""
    if header.seq <= st.last_seq:
        what = "duplicate" if header.seq == st.last_seq else "out of order"
        return f"{what}: seq {header.seq} after {st.last_seq}"
    if st.last_seq >= 0 and header.seq > st.last_seq + MAX_SEQ_JUMP:
        # A forged far-future seq would make every later real frame "out of order".
        return (f"seq jumps from {st.last_seq} to {header.seq} "
                f"(more than {MAX_SEQ_JUMP} frames lost?)")
    if index < 0 or index <= st.last_index:
        return f"frame index {index} is not after the last frame's {st.last_index}"
    if index > max(st.last_index, 0) + MAX_INDEX_JUMP:
        return (f"frame index jumps from {st.last_index} to {index} "
                f"(more than {MAX_INDEX_JUMP})")
    if st.rows and header.timestamp <= st.rows[-1].timestamp:
        return (f"timestamp {header.timestamp:.6f} is not after the "
                f"last frame's {st.rows[-1].timestamp:.6f}")
    return None

"""The robot's side of its link: everything it sends goes through one emulated link (frames,
keyframe uploads and control messages share it, so a robot never sends faster than its
link), and frames go on a send thread of their own."""

from __future__ import annotations

import queue
import threading
import time
from typing import Any

from fleetslam.edge.flow import FlowWindow
from fleetslam.edge.report import RobotReport
from fleetslam.planner.online import OnlinePlanner
from fleetslam.transport import keys, protocol
from fleetslam.transport.link import EmulatedLink


# Frames coded and waiting for the link (FrameOutbox).
FRAMES_WAITING = 1


class Sender:
    """Sends on the link and records each frame and upload in the report (``sends``); an
    adaptive robot's planner learns its link from how long the sends take."""

    def __init__(self, robot_id: str, link: EmulatedLink, report: RobotReport,
                 planner: OnlinePlanner | None) -> None:
        self.robot_id = robot_id
        self.link = link
        self.report = report
        self.planner = planner
        self.t0 = time.monotonic()  # the report's time origin: set when the first frame is read

    def send(self, key: str, data: bytes) -> bool:
        """A frame or keyframe upload; blocks at link speed. False if the link lost it."""
        start = time.monotonic()
        delivered = self.link.send(key, data)
        end = time.monotonic()
        if self.planner is not None:
            self.planner.meter.sent(len(data), start, end)
        # list.append is atomic: the send and uploader threads both record here.
        self.report.sends.append((start - self.t0, end - self.t0, len(data),
                                  "keyframe" if key == keys.keyframe(self.robot_id) else "frame",
                                  delivered))
        return delivered

    def control(self, message: dict[str, Any]) -> None:
        data = protocol.encode(message)
        self.report.control_bytes += len(data)
        self.link.send(keys.control(self.robot_id), data)

    def close(self) -> None:
        self.link.close()


class FrameOutbox:
    """The send thread: the link sends frame i while the stages work on frame i+1 (a robot's
    NIC and CPU run side by side). At most one frame waits for the link: the robot does not
    run ahead of it, and the frame being coded names references acknowledged as late as
    possible (a queue of two: round trip median 66-71 ms, 21.0-21.3 kB a frame; of one:
    46-49 ms, 20.6 kB; bench/offload.py at point 3). A frame the link loses leaves the
    flow-control window."""

    def __init__(self, sender: Sender, window: FlowWindow) -> None:
        self.sender = sender
        self.window = window
        self._queue: queue.Queue = queue.Queue(maxsize=FRAMES_WAITING)
        self._thread = threading.Thread(target=self._run, name=f"robot-{sender.robot_id}-send",
                                        daemon=True)
        self._thread.start()

    def put(self, seq: int, data: bytes) -> None:
        """Blocks while a frame waits for the link."""
        self._queue.put((seq, data))

    def drain(self) -> None:
        """Wait until every frame put so far is on the link."""
        self._queue.join()

    def close(self) -> None:
        """Send what is queued, then end the thread."""
        self._queue.put(None)
        self._thread.join()

    def _run(self) -> None:
        while (item := self._queue.get()) is not None:
            seq, data = item
            if not self.sender.send(keys.frame(self.sender.robot_id), data):
                self.sender.report.frames_lost_on_link += 1
                self.window.lost(seq)
            self._queue.task_done()
        self._queue.task_done()

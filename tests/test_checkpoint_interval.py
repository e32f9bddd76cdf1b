"""transport.checkpoint_interval_s: keyframe checkpoints asked within the interval wait and
are captured once at its end; none is acknowledged or handed to the merger before a
checkpoint that holds it is on disk, and none is forgotten."""

from __future__ import annotations

import time

from fleetslam.cloud.session.checkpoint_writer import CheckpointWriter
from fleetslam.cloud.session.store import CHECKPOINT, CloudStore
from fleetslam.wire.data_tree import Capture


def test_keyframe_checkpoints_within_the_interval_are_captured_once(tmp_path):
    store = CloudStore(tmp_path)
    captured: list[int] = []

    def snapshot() -> Capture:
        captured.append(len(captured))
        return Capture(f'{{"capture": {len(captured)}}}', {})

    merged: list[str] = []
    writer = CheckpointWriter("r0", store, snapshot, -1,
                              keyframe_sink=lambda summary, poses: merged.append(summary),
                              interval_s=0.5)
    writer.start()
    try:
        first = writer.checkpoint(10, ("kf1", None), now=False)  # nothing before: at once
        writer.checkpoint(14, ("kf2", None), now=False)
        last = writer.checkpoint(18, ("kf3", None), now=False)
        assert captured == [0]
        wait = writer.due_in()
        assert wait is not None and 0.0 < wait <= 0.5
        assert writer.wait_for_number(first, 5.0)
        assert not writer.wait_for_frame(14, 0.05)  # kf2 is not on disk: not acknowledged
        assert merged == ["kf1"]
        writer.capture_due()  # not due yet: nothing happens
        assert captured == [0]
        time.sleep(writer.due_in() or 0.0)
        writer.capture_due()
        assert captured == [0, 1] and writer.due_in() is None
        assert writer.wait_for_number(last, 5.0) and writer.wait_for_frame(18, 0.0)
        assert merged == ["kf1", "kf2", "kf3"]
        assert (store.robot_dir("r0") / CHECKPOINT).exists()
        # An asked-for checkpoint (the end's) is captured at once with what waits.
        writer.checkpoint(22, ("kf4", None), now=False)
        end = writer.checkpoint(23)
        assert captured == [0, 1, 2] and writer.due_in() is None
        assert writer.wait_for_number(end, 5.0) and merged[-1] == "kf4"
    finally:
        writer.close(5.0)


def test_no_interval_is_a_checkpoint_per_keyframe(tmp_path):
    captured: list[int] = []

    def snapshot() -> Capture:
        captured.append(1)
        return Capture("{}", {})

    writer = CheckpointWriter("r0", CloudStore(tmp_path), snapshot, -1, interval_s=0.0)
    writer.start()
    try:
        for i in range(3):
            writer.checkpoint(i, None, now=False)
        assert len(captured) == 3 and writer.due_in() is None
    finally:
        writer.close(5.0)

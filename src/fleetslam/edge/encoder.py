"""A frame on the robot: run the stages before the offloading point, then encode the state
there as a frame message, inter-coded against frames the cloud holds (``wire/inter.py``)."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from fleetslam.camera import Camera
from fleetslam.config import Config
from fleetslam.datasets.source import Frame
from fleetslam.edge.report import RobotReport
from fleetslam.pipeline.split import INTER_POINTS, Sides, Stage, StageTimer, run_stages
from fleetslam.pipeline.states import CapturedFrame, TrackedFrame
from fleetslam.transport.protocol import Welcome
from fleetslam.wire.frames import encode_frame_message
from fleetslam.wire.inter import InterEncoder, InterStats, reference_of, warm_up
from fleetslam.wire.paper_yaml import write_paper_yaml
from fleetslam.wire.pose_deltas import PoseDeltaEncoder


def prepare(config: Config, offload_at: int | None) -> None:
    """Pay the first inter-coded frame's one-time costs (its search's imports) now: before
    a live camera starts, so they hold back no frame. ``offload_at`` None: an adaptive robot,
    which may switch to any point."""
    if config.wire.inter_frame and (offload_at is None or offload_at in INTER_POINTS):
        warm_up()


class FrameEncoder:
    """The robot's stages (and their state, ``sides``) and its inter-frame coder, which
    learns from the cloud's answers which frames it holds as references."""

    def __init__(self, robot_id: str, camera: Camera, config: Config, stages: list[Stage],
                 sides: Sides, report: RobotReport, paper_yaml_dir: Path | None = None) -> None:
        self.robot_id = robot_id
        self.camera = camera
        self.config = config
        self.stages = stages
        self.sides = sides
        self.report = report
        # Also write each frame as the paper's YAML file (inspection, old tools).
        self.paper_yaml_dir = paper_yaml_dir
        self.timer = StageTimer()
        self.inter = InterEncoder(config.wire)
        self.poses = PoseDeltaEncoder()  # a robot that tracks itself: its keyframes' poses
        self.next_seq = 0  # the seq of the next frame to encode
        self._encode_ms: list[float] = []

    def encode(self, frame: Frame, k: int, seq: int) -> bytes:
        """Frame ``frame`` through the stages before point ``k``, as message ``seq``."""
        start = time.perf_counter()
        cpu_start = time.thread_time()
        state = run_stages(self.stages[:k],
                           CapturedFrame(frame.index, frame.timestamp, frame.rgb, frame.depth_m),
                           self.sides, self.timer)
        encode_start = time.perf_counter()
        self.next_seq = seq + 1
        refs = self.inter.choose(seq) if k in INTER_POINTS else []
        stats = InterStats()
        table = np.asarray(state.keyframe_poses, np.float64) \
            if isinstance(state, TrackedFrame) and state.sends_keyframe else None
        delta = self.poses.choose(table) if table is not None else None
        data = encode_frame_message(state, k, self.robot_id, seq, self.camera,
                                    self.config.wire, refs, stats, delta)
        if table is not None:
            self.poses.sent(seq, table, delta)
        if k in INTER_POINTS:
            self.inter.sent(seq, reference_of(state), len(refs))
            self.inter.record(stats)
        now = time.perf_counter()
        self._encode_ms.append(1000.0 * (now - encode_start))
        self.report.robot_compute_s += now - start
        self.report.frame_cpu_ms.append(round(1000.0 * (time.thread_time() - cpu_start), 3))
        if self.paper_yaml_dir is not None:
            write_paper_yaml(self.paper_yaml_dir / f"{frame.index:06d}.yml", state)
        return data

    @property
    def features(self) -> int:
        """Features per frame the robot's Extract keeps (orb.n_features without one)."""
        edge = self.sides.edge
        return edge.features if edge is not None else self.config.orb.n_features

    def use_features(self, n: int) -> None:
        """From the next frame on, Extract keeps ``n`` features (an adaptive robot's choice;
        at point 0 the cloud extracts, with its own setting)."""
        if self.sides.edge is not None:
            self.sides.edge.n_features = n

    # -- what the cloud says about references ---------------------------------------------

    def held(self, seq: int) -> None:
        """The cloud holds frame ``seq`` (decoded it, or answered it): a reference from now on."""
        self.inter.acked(seq)

    def tracked(self, seq: int) -> None:
        """The cloud tracked frame ``seq`` (its feedback): a keyframe's poses are a base."""
        self.poses.tracked(seq)

    def references_lost(self) -> None:
        """The cloud holds none of the frames sent so far (a missing reference, a takeover):
        intra frames until a frame sent from now on is acknowledged, whole keyframe pose
        tables until one is tracked."""
        self.inter.refused(self.next_seq)
        self.poses.lost()

    def restart(self, welcome: Welcome) -> None:
        """A new or resumed session: no frame acknowledged before is a reference."""
        self.inter.set_cloud_ring(welcome.reference_frames)
        self.inter.restart(welcome.next_seq)
        self.poses.restart(welcome.pose_deltas)

    def record(self, report: RobotReport) -> None:
        """The run's end: stage and encoding times, the inter-frame coding's counts."""
        report.robot_stage_ms = self.timer.mean_ms()
        if self._encode_ms:
            report.encode_ms_mean = float(np.mean(self._encode_ms))
            report.encode_ms_p95 = float(np.percentile(self._encode_ms, 95))
        report.inter_coding = self.inter.counts.summary()
        if self.poses.counts.whole_tables or self.poses.counts.delta_tables:
            report.inter_coding.update(self.poses.counts.summary())

"""The robot's online planner: its link measurement, and choices that keep up with the
camera at the best quality the measured link allows, without flapping."""

from __future__ import annotations

import pytest

from fleetslam.config import PlannerConfig
from fleetslam.planner.online import LinkMeter, OnlinePlanner, Setting
from fleetslam.planner.profile import Profile
from fleetslam.transport.link import parse_link_trace
from fleetslam.transport.protocol import Hello


def _profile() -> Profile:
    """Round numbers of the shape measured on 7-Scenes (bench: plan --save-profile)."""
    return Profile(source="test", label="measured", frames=100,
                   stages=["extract", "describe", "associate_depth", "match",
                           "estimate_pose", "decide_keyframe"],
                   stage_ms=[4.0, 3.0, 0.7, 4.0, 2.0, 2.5], stage_ms_p95=[5.0] * 6,
                   frame_bytes=[536e3, 275e3, 147e3, 32.7e3, 43e3, 43.2e3, 0.2e3],
                   keyframe_bytes=40e3, keyframe_fraction=0.19)


def test_the_link_meter_counts_busy_time_once_when_sends_queue():
    meter = LinkMeter(window_s=100.0)
    # Three 125 kB messages at 1 Mbit/s, the second and third queued behind the first.
    meter.sent(125_000, 0.0, 1.0)
    meter.sent(125_000, 0.5, 2.0)
    meter.sent(125_000, 0.9, 3.0)
    assert meter.bandwidth_mbps() == pytest.approx(1.0)
    meter.round_trip(0.2)
    assert meter.round_trip_s() == pytest.approx(0.2)
    assert LinkMeter(1.0).bandwidth_mbps() is None  # nothing measured yet


def test_the_planner_keeps_full_quality_on_a_good_link_and_degrades_on_a_bad_one():
    cfg = PlannerConfig()
    planner = OnlinePlanner(_profile(), cfg, Setting(3, 1000, 1))
    assert planner.choose(20.0) == Setting(3, 1000, 1)
    slow = planner.choose(1.0)
    assert slow.k == 3 and (slow.features < 1000 or slow.frame_step > 1)
    planner.current = slow
    assert planner.choose(1.05) == slow  # noise does not make it flap
    assert planner.choose(20.0) == Setting(3, 1000, 1)  # quality comes back at once


def test_replan_records_what_it_measured_and_chose():
    cfg = PlannerConfig()
    planner = OnlinePlanner(_profile(), cfg, Setting(3, 1000, 1))
    assert planner.replan(30) == Setting(3, 1000, 1)  # nothing measured: keep the setting
    for i in range(5):
        planner.meter.sent(50_000, 0.4 * i, 0.4 * (i + 1))  # 1 Mbit/s, back to back
    planner.replan(60)
    assert planner.history[-1]["measured_mbps"] == pytest.approx(1.0, rel=0.01)
    assert planner.history[-1]["changed"]


def test_hello_and_trace_are_checked():
    camera = {"fx": 525.0, "fy": 525.0, "cx": 319.5, "cy": 239.5}
    base = {"type": "hello", "protocol": 1, "camera": camera}
    assert Hello.parse({**base, "offload_at": 3, "adaptive": True}).adaptive
    with pytest.raises(ValueError, match="cannot start at 6"):
        Hello.parse({**base, "offload_at": 6, "adaptive": True})
    with pytest.raises(ValueError, match="true or false"):
        Hello.parse({**base, "offload_at": 3, "adaptive": "yes"})
    assert parse_link_trace("0:10,300:1,700:10") == [(0, 10.0), (300, 1.0), (700, 10.0)]
    for bad in ("0:10,0:1", "0:-1", "a:b"):
        with pytest.raises(ValueError, match="link trace"):
            parse_link_trace(bad)


def test_the_planners_feature_count_reaches_extract_without_touching_the_config(
        tmp_path_factory):
    """An adaptive robot's feature count is the robot's front end's, from the next frame on;
    the config (one object, read everywhere) is not a channel for it."""
    from conftest import small_scene

    from fleetslam.config import Config
    from fleetslam.datasets.tum import RgbdSequence
    from fleetslam.edge.robot import Robot
    from fleetslam.pipeline.split import run_stages
    from fleetslam.pipeline.states import CapturedFrame

    folder = small_scene(tmp_path_factory, 2)[0]
    config = Config()
    robot = Robot("r1", RgbdSequence(folder), str(folder), 3, config, show_progress=False)
    frame = RgbdSequence(folder)[0]
    captured = CapturedFrame(frame.index, frame.timestamp, frame.rgb, frame.depth_m)
    extract = robot.encoder.stages[:1]
    full = run_stages(extract, captured, robot.encoder.sides)
    assert robot.encoder.features == config.orb.n_features
    robot.encoder.use_features(200)
    fewer = run_stages(extract, captured, robot.encoder.sides)
    assert robot.encoder.features == 200 and len(fewer.keypoints) <= 200 < len(full.keypoints)
    assert config.orb.n_features == Config().orb.n_features

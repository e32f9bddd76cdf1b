"""The robot re-plans while it runs: it measures its link (how fast its sends actually go
out, and the round trip of the cloud's feedback), and every ``replan_frames`` frames picks
the split point, the number of ORB features and the frame step (send every n-th frame) that
keep up best, by the same time model as ``fleetslam plan``.

Only the points the cloud can switch between frame by frame are offered (0-3: the cloud holds
the map at all of them). Fewer features and skipped frames cost tracking quality, so they are
used only when no point at full quality keeps up with the camera (``target_fps``); a new
setting must promise ``switch_gain`` times the throughput of the current one, so noise in the
measurement does not make the robot flap between settings.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from fleetslam.config import PlannerConfig
from fleetslam.planner.model import Link, candidates
from fleetslam.planner.profile import Profile


@dataclass(frozen=True)
class Setting:
    k: int
    features: int
    frame_step: int


@dataclass
class Prediction:
    setting: Setting
    bytes_per_frame: float
    throughput_fps: float  # camera frames per second the stream covers (sent x step)
    energy_j: float  # paper eq. 16 per frames_per_unit sent frames


class LinkMeter:
    """The link as the robot sees it, over its last sends: the bytes it put out over the time the
    link was busy with them (the union of its send calls: a send blocks while its bytes go
    out, and queued sends overlap), and the feedback round trips."""

    def __init__(self, window_s: float, window_sends: int = 20) -> None:
        self.window_s = window_s
        self.window_sends = window_sends
        self._sends: deque[tuple[float, float, int]] = deque()  # (start, end, bytes)
        self._round_trips: deque[tuple[float, float]] = deque()
        self._lock = threading.Lock()

    def sent(self, size: int, start: float, end: float) -> None:
        with self._lock:
            self._sends.append((start, end, size))
            while end - self._sends[0][1] > self.window_s or \
                    len(self._sends) > self.window_sends:
                self._sends.popleft()

    def round_trip(self, seconds: float) -> None:
        now = time.monotonic()
        with self._lock:
            self._round_trips.append((now, seconds))
            while now - self._round_trips[0][0] > self.window_s:
                self._round_trips.popleft()

    def bandwidth_mbps(self) -> float | None:
        with self._lock:
            sends = sorted(self._sends)
        if len(sends) < 3:
            return None
        busy, reach = 0.0, -np.inf
        for start, end, _ in sends:  # union of the send intervals
            busy += max(0.0, end - max(start, reach))
            reach = max(reach, end)
        # Sends that went out at once (an unshaped link) say only that the link is fast.
        if busy <= 1e-4:
            return None
        return sum(size for _, _, size in sends) * 8 / busy / 1e6

    def round_trip_s(self) -> float | None:
        with self._lock:
            values = [v for _, v in self._round_trips]
        return float(np.median(values)) if values else None


def predict(profile: Profile, cfg: PlannerConfig, setting: Setting, bandwidth_mbps: float
            ) -> Prediction:
    """The planner's model (``model.candidates``) of one setting: its point at its share of
    the features; the frame step multiplies the camera frames the stream covers."""
    c = candidates(profile, Link(bandwidth_mbps), cfg,
                   feature_scale=setting.features / cfg.feature_options[0])[setting.k]
    return Prediction(setting, c.bytes_per_frame,
                      min(c.fps, cfg.target_fps) * setting.frame_step, c.energy_j)


class OnlinePlanner:
    def __init__(self, profile: Profile, cfg: PlannerConfig, start: Setting) -> None:
        self.profile = profile
        self.cfg = cfg
        self.current = start
        self.meter = LinkMeter(cfg.link_window_s, cfg.link_window_sends)
        self.history: list[dict[str, Any]] = []

    def settings(self) -> list[Setting]:
        return [Setting(k, f, m) for k in self.cfg.online_points
                for f in self.cfg.feature_options for m in self.cfg.frame_step_options]

    def choose(self, bandwidth_mbps: float) -> Setting:
        """The best quality that keeps up with the camera (every frame before fewer
        features, then the least energy); if none does, the most throughput."""
        cfg = self.cfg
        predictions = [predict(self.profile, cfg, s, bandwidth_mbps) for s in self.settings()]
        keeping_up = [p for p in predictions if p.throughput_fps >= cfg.target_fps - 1e-9]
        if keeping_up:
            best = min(keeping_up, key=lambda p: (p.setting.frame_step, -p.setting.features,
                                                  p.energy_j))
        else:
            best = max(predictions, key=lambda p: (round(p.throughput_fps, 6),
                                                   -p.setting.frame_step, p.setting.features,
                                                   -p.energy_j))
        now = predict(self.profile, cfg, self.current, bandwidth_mbps)
        if best.setting == self.current:
            return self.current
        # A better quality that keeps up is taken at once; more throughput only if it is
        # clearly more (the measurement is noisy).
        quality_up = bool(keeping_up) and now.throughput_fps >= cfg.target_fps - 1e-9
        if quality_up or best.throughput_fps >= cfg.switch_gain * now.throughput_fps:
            return best.setting
        return self.current

    def replan(self, frame_index: int) -> Setting:
        """Called every ``replan_frames`` frames: the setting for the next frames."""
        bandwidth = self.meter.bandwidth_mbps()
        chosen = self.current if bandwidth is None else self.choose(bandwidth)
        self.history.append({"frame": frame_index, "measured_mbps": bandwidth,
                             "round_trip_ms": None if self.meter.round_trip_s() is None
                             else 1000 * self.meter.round_trip_s(),
                             **asdict(chosen), "changed": chosen != self.current})
        self.current = chosen
        return chosen

"""A worker's measured load (cloud/coordination/worker_load.py): reports are checked before use, a
robot granted since a report weighs the configured cost until it is measured, equal loads are
decided by the robot's hash (robots spread), and the meter sees a busy process."""

from __future__ import annotations

import json
import os
import time

import pytest

from fleetslam.cloud.coordination.worker_load import CpuMeter, LoadReport, WorkerLoads, parse_report
from fleetslam.config import PlacementConfig


def test_a_report_is_checked_before_it_is_used():
    assert parse_report(b'{"busy": 1.25, "owned": 3}') == LoadReport(1.25, 3)
    assert parse_report(b'{"busy": 1.25, "owned": 3, "full": true}') == LoadReport(1.25, 3, True)
    for data, reason in [(b"x" * 300, "bytes"), (b"{", "not JSON"), (b"[1]", "object"),
                         (b'{"busy": -1, "owned": 0}', "busy"),
                         (json.dumps({"busy": float("nan"), "owned": 0}).encode(), "busy"),
                         (b'{"busy": 0.5, "owned": true}', "owned"),
                         (b'{"busy": true, "owned": 1}', "busy"),
                         (b'{"busy": 0.5}', "owned"),
                         (b'{"busy": 0.5, "owned": 1, "full": 1}', "full")]:
        with pytest.raises(ValueError, match=reason):
            parse_report(data)


class Counts:
    """A meter, a placement's holdings and a session table's robots at work, as set."""

    def __init__(self, busy: float = 0.0, held: int = 0, at_work: int = 0) -> None:
        self.cores, self.robots_held, self.robots_at_work = busy, held, at_work
        self.room = True

    def busy(self) -> float:
        return self.cores

    def has_room(self) -> bool:
        return self.room

    def held(self) -> int:
        return self.robots_held

    def at_work(self) -> int:
        return self.robots_at_work


def test_robots_granted_since_a_report_weigh_the_configured_cost():
    cfg = PlacementConfig(robot_cost_cores=0.4)
    loads = WorkerLoads("w0", cfg, Counts(), Counts())
    loads.reports = {"w0": LoadReport(1.0, 2), "w1": LoadReport(0.2, 0)}
    assert loads.score("w0", 2) == pytest.approx(1.0)
    assert loads.score("w0", 4) == pytest.approx(1.8)  # two granted since it measured
    assert loads.score("w0", 1) == pytest.approx(1.0)  # one ended: measured next time
    assert loads.score("w9", 1) == pytest.approx(0.4)  # never heard: its robots' cost
    # The least loaded first; within EQUAL_CORES, the robot's hash decides, so robots
    # arriving at equally loaded workers go to both.
    assert loads.ranking("r0", {"w0": 1.0, "w1": 0.2}) == ["w1", "w0"]
    firsts = {loads.ranking(f"r{i}", {"w0": 0.31, "w1": 0.30})[0] for i in range(16)}
    assert firsts == {"w0", "w1"}


def test_the_workers_are_all_full_only_when_every_report_says_so():
    """This worker as it is now, the others as their last reports say; a worker never
    heard from counts as having room (a robot is then not told the cloud is full)."""
    meter = Counts()
    loads = WorkerLoads("w0", PlacementConfig(), meter, Counts())
    loads.reports = {"w1": LoadReport(1.0, 2, True), "w2": LoadReport(1.0, 2, False)}
    meter.room = False
    assert loads.all_full(["w0", "w1"])
    assert not loads.all_full(["w0", "w1", "w2"])
    assert not loads.all_full(["w0", "w1", "w9"])  # never heard
    meter.room = True
    assert not loads.all_full(["w0", "w1"])


def test_a_robot_weighs_the_same_before_and_after_its_workers_report(monkeypatch):
    """A robot granted since a report counts the configured cost; the next report counts it
    as its meter does (a new robot at work: the configured cost), never both. Reports that
    left it out until held a whole window while the meter counted it weighed it twice: the
    worker that had reported looked busier, and robots arriving together went 2 + 6."""
    import fleetslam.cloud.coordination.worker_load as worker_load

    cfg = PlacementConfig(load_window_s=5.0, robot_cost_cores=0.4)
    held, meter = Counts(), Counts()
    loads = WorkerLoads("w0", cfg, meter, held)
    monkeypatch.setattr(worker_load, "put", lambda *a, **k: None)
    loads.report()
    held.robots_held = 2  # granted since: not in the report yet
    assert loads.score("w0", 2) == pytest.approx(0.8)
    meter.cores = 0.8  # at work, as the CPU meter weighs robots too new to be measured
    assert loads.report().owned == 2
    assert loads.score("w0", 2) == pytest.approx(0.8)
    assert loads.score("w0", 3) == pytest.approx(1.2)  # one more granted since


def test_the_meter_sees_a_busy_process_and_robots_gone_quiet_at_once():
    robots = Counts(at_work=1)
    meter = CpuMeter(os.getpid(), window_s=0.2, robots=robots, robot_cost=0.4)
    assert meter.busy() >= 0.4  # a robot too new to be measured: its configured cost
    end = time.monotonic() + 1.0
    while time.monotonic() < end:
        sum(i * i for i in range(10_000))
    busy = meter.busy()
    assert busy > 0.2  # one core busy, less what a loaded machine takes of it
    robots.robots_at_work = 0
    assert meter.busy() < 0.05 * busy  # its robot went quiet: nothing left to weigh
    robots.robots_at_work = 1
    time.sleep(1.2)
    assert meter.busy() < 0.2  # idle for six windows


def test_robots_arriving_together_weigh_their_cost_until_the_average_takes_them_in():
    """Ten robots granted at once to an idle worker: a fifth of a window later the averaged
    robot count is about two, yet the ten have not cost anything measurable yet; they weigh
    the configured cost each until the average has them (before: the idle CPU scaled to ten
    robots, near nothing, and the next robots of the fleet all came here)."""
    robots = Counts(at_work=0)
    meter = CpuMeter(os.getpid(), window_s=0.5, robots=robots, robot_cost=0.4)
    time.sleep(0.15)
    meter.busy()  # idle, no robot
    robots.robots_at_work = 10
    time.sleep(0.1)
    # 10 x 0.4, less the 2 (5 if the sleep overran threefold) the average has taken in.
    assert meter.busy() > 1.6
    time.sleep(2.5)  # five windows of an idle process: measured, nearly nothing
    assert meter.busy() < 0.2


def test_a_fleet_that_follows_one_just_ended_weighs_as_new():
    """Ten robots at work for three windows, all gone quiet, then ten others at once (a
    shift ends, the next starts): the new ones weigh the configured cost each, not the
    places of the quiet ones in an average that still held them (8 + 12 of 20 robots)."""
    robots = Counts(at_work=10)
    meter = CpuMeter(os.getpid(), window_s=2.0, robots=robots, robot_cost=0.4)
    end = time.monotonic() + 1.5
    while time.monotonic() < end:
        sum(i * i for i in range(10_000))
        meter.busy()
    robots.robots_at_work = 0
    assert meter.busy() < 0.05  # gone quiet
    robots.robots_at_work = 10
    time.sleep(0.1)
    # 10 x 0.4 less the half robot (two if the sleep overran fivefold) the average took in;
    # an average still holding the quiet ten gave about 2.3.
    assert meter.busy() > 2.8


def test_niced_background_work_is_not_a_robot_s_load():
    """A worker's niced children (local BA, the place search) yield the cores to tracking:
    placement's meter leaves them out; the process tree's total (the benchmarks') keeps
    them."""
    import subprocess
    import sys

    from fleetslam.cloud.coordination.worker_load import tree_cpu_seconds

    # The child spins for CPU time, not wall time: on a loaded machine a niced child gets
    # little of a core, and the test waits (a second at a time) until it has spun.
    spin = ("import time\nend = time.monotonic() + 20\n"
            "while time.process_time() < 0.6 and time.monotonic() < end: pass\n")
    child = subprocess.Popen([sys.executable, "-c", f"import os; os.nice(5)\n{spin}"])
    try:
        start_all = tree_cpu_seconds(os.getpid())
        start_ours = tree_cpu_seconds(os.getpid(), unniced_only=True)
        for _ in range(15):
            time.sleep(1.0)
            spent_all = tree_cpu_seconds(os.getpid()) - start_all
            if spent_all > 0.3 or child.poll() is not None:
                break
        spent_ours = tree_cpu_seconds(os.getpid(), unniced_only=True) - start_ours
    finally:
        child.wait(30)
    assert spent_all > 0.3  # the niced child spun
    assert spent_ours < 0.1  # this process slept

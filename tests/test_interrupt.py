"""Ctrl-C keeps the work done: an interrupted ``fleetslam run`` writes the trajectories it
tracked, a summary marked interrupted and the report, and its --out is reused only with
--overwrite; a cloud stopped by Ctrl-C (sent to its whole process group, as a terminal
does) stops in one line, its local-BA workers quiet."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time

from conftest import TUM_RPY, require, wait_for

from fleetslam.io.trajectory import read_tum_trajectory
from fleetslam.launch import free_endpoint, stop


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "fleetslam.cli", *args]


def _collect(stream, lines: list[str]) -> threading.Thread:
    thread = threading.Thread(target=lambda: lines.extend(stream), daemon=True)
    thread.start()
    return thread


def test_ctrl_c_in_run_keeps_what_was_tracked(tmp_path):
    source = str(require(TUM_RPY))
    out = tmp_path / "run"
    run = subprocess.Popen(_cli("run", "--robot", source, "--out", str(out)), text=True,
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    err: list[str] = []
    reader = _collect(run.stderr, err)
    try:
        wait_for(lambda: any("tracking: " in line for line in err), 60, "tracking progress")
        time.sleep(2.0)  # a few frames tracked
        run.send_signal(signal.SIGINT)
        stdout = run.communicate(timeout=60)[0]
    finally:
        stop(run, 2.0)
    reader.join(5)
    stderr = "".join(err)
    assert run.returncode == 130, stderr
    assert "Traceback" not in stderr
    summary = json.loads((out / "summary.json").read_text())
    tracked = summary["interrupted"]["frames_tracked"]["r0"]
    assert 0 < tracked < summary["interrupted"]["frames_given"]["r0"] == 150
    times, _ = read_tum_trajectory(out / "r0" / "trajectory.tum")
    assert len(times) == tracked == summary["robots"][0]["frames"]
    assert "interrupted" in (out / "report" / "report.html").read_text()
    assert "interrupted (Ctrl-C)" in stdout and f"report: {out}/report/report.html" in stdout

    # The same --out again: refused in one line naming the flag; the interrupted run kept.
    again = subprocess.run(_cli("--quiet", "run", "--robot", f"{source}:0-3", "--out",
                                str(out)), capture_output=True, text=True, timeout=60)
    assert again.returncode == 2
    assert again.stderr.strip() == (f"fleetslam: error: --out {out}: the folder exists; give "
                                    f"another --out, or add --overwrite to replace it")
    assert "interrupted" in json.loads((out / "summary.json").read_text())
    # With --overwrite: replaced by the new run.
    again = subprocess.run(_cli("--quiet", "run", "--robot", f"{source}:0-3", "--out",
                                str(out), "--overwrite"), capture_output=True, text=True,
                           timeout=60)
    assert again.returncode == 0, again.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert "interrupted" not in summary and summary["robots"][0]["frames"] == 4


def test_overwrite_replaces_only_a_run_folder(tmp_path):
    """--overwrite on a folder of other files: refused, the files kept."""
    other = tmp_path / "notes"
    other.mkdir()
    (other / "keep.txt").write_text("mine")
    result = subprocess.run(_cli("--quiet", "run", "--robot", str(require(TUM_RPY)), "--out",
                                 str(other), "--overwrite"),
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert result.stderr.strip() == (f"fleetslam: error: --out {other}: not a run folder (no "
                                     f"summary.json): --overwrite replaces only a run folder; "
                                     f"give another --out")
    assert (other / "keep.txt").read_text() == "mine"


def test_ctrl_c_stops_the_cloud_in_one_line(tmp_path):
    cloud = subprocess.Popen(_cli("cloud", "--listen", free_endpoint(), "--out",
                                  str(tmp_path / "store")),
                             stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                             start_new_session=True)  # its own group: Ctrl-C reaches all
    lines: list[str] = []
    reader = _collect(cloud.stdout, lines)
    try:
        wait_for(lambda: any("listening on" in line for line in lines), 60, "the cloud")
        time.sleep(5.0)  # its local-BA worker process started and waits for work
        os.killpg(cloud.pid, signal.SIGINT)
        cloud.wait(60)
    finally:
        stop(cloud, 2.0)
    reader.join(5)
    output = "".join(lines)
    assert cloud.returncode == 0, output
    assert "Traceback" not in output and "KeyboardInterrupt" not in output
    assert output.rstrip().splitlines()[-1] == "fleetslam cloud: stopped"


def test_demo_reuses_out_only_with_overwrite(tmp_path):
    out = tmp_path / "demo"
    out.mkdir()
    (out / "summary.json").write_text("{}")
    result = subprocess.run(_cli("--quiet", "demo", "--in-process", "--frames", "4", "--scene",
                                 str(tmp_path / "scene"), "--out", str(out)),
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert result.stderr.strip() == (f"fleetslam: error: --out {out}: the folder exists; give "
                                     f"another --out, or add --overwrite to replace it")
    assert (out / "summary.json").read_text() == "{}"

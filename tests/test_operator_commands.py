"""What `fleetslam status` and `fleetslam merge` print against a running cloud: a table and
plain lines (no Python dict), the merge's tables without columns empty for every robot, and
where the cloud wrote the outputs and the report."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import fleetslam
from conftest import TUM_RPY, require

from fleetslam.cli import main
from fleetslam.launch import free_endpoint, start_cloud, start_robot, stop
from fleetslam.transport.zenoh_session import wait_until_reachable

# Two robots on overlapping parts of one recording: they join.
SOURCES = (":0-19", ":10-29")
MERGED_WITHIN_S = 60.0


def test_status_and_merge_say_what_and_where(tmp_path, capsys, monkeypatch):
    # Robots given relative sources (the cloud's summary must name them absolutely); the
    # processes still import this fleetslam from the other directory.
    package = str(Path(fleetslam.__file__).resolve().parents[1])
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([package, os.environ.get("PYTHONPATH", "")]))
    # The data reached through a symlink, as a CI's data mount often is: the cloud names the
    # folder the link resolves to.
    (tmp_path / "data").symlink_to(require(TUM_RPY).parent, target_is_directory=True)
    monkeypatch.chdir(tmp_path)
    scene = [f"data/{TUM_RPY.name}{frames}" for frames in SOURCES]
    endpoint, store = free_endpoint(), tmp_path / "store"
    cloud = start_cloud(endpoint, store, tmp_path / "cloud.log")
    try:
        # An operator's command says at once that nothing listens: the cloud is up first.
        wait_until_reachable(endpoint, 60.0)
        # Before any robot finished: one line saying there is nothing to merge yet.
        assert main(["--quiet", "merge", "--connect", endpoint]) != 0
        early = capsys.readouterr().err
        assert "no robot has finished yet" in early and "Traceback" not in early, early
        robots = [start_robot(endpoint, f"r{i}", folder, 3, tmp_path / f"r{i}.log")
                  for i, folder in enumerate(scene)]
        for i, robot in enumerate(robots):
            assert robot.wait(120) == 0, (tmp_path / f"r{i}.log").read_text()
        capsys.readouterr()
        # The robots' ends do not wait for the merger's place searches (a niced process):
        # the status says what is still merging, and the groups are final once it does not.
        deadline = time.monotonic() + MERGED_WITHIN_S
        while True:
            assert main(["--quiet", "status", "--connect", endpoint]) == 0
            status = capsys.readouterr().out
            if "still merging" not in status or time.monotonic() > deadline:
                break
            time.sleep(0.5)
        assert "{" not in status and "[" not in status, status
        assert "still merging" not in status, f"not merged within {MERGED_WITHIN_S} s: {status}"
        assert "map groups (merger of worker " in status and "): r0+r1; " in status
        assert main(["--quiet", "merge", "--connect", endpoint]) == 0
        merged = capsys.readouterr().out
    finally:
        stop(cloud)
    assert "Traceback" not in (tmp_path / "cloud.log").read_text()
    folder = store.resolve()
    assert f"outputs in {folder}/ on the cloud's machine (summary.json" in merged
    assert f"report: {folder}/report/report.html (made without ground truth" in merged
    assert (folder / "report" / "report.html").is_file()
    sources = [r["source"] for r in json.loads((folder / "summary.json").read_text())["robots"]]
    # Absolute, the frames kept; compared resolved (../shared itself may be a symlink).
    assert all(Path(s.rpartition(":")[0]).is_absolute() for s in sources), sources
    assert [(Path(s.rpartition(":")[0]).resolve(), s.rpartition(":")[2]) for s in sources] == \
        [(TUM_RPY.resolve(), frames[1:]) for frames in SOURCES]
    # No ground truth in the cloud and no robot reports: those columns are left out, named.
    assert "ATE RMSE cm" not in merged.split("not shown")[0]
    assert "not shown (no value for any robot): ATE RMSE cm" in merged
    for line in merged.splitlines():
        cells = line.split()
        assert not cells or cells.count("-") < len(cells) // 2, line
    # Issue 45 items 3 and 5: the merge's own time (a wall time read 0.0 s); a reason a
    # robot is not merged is no column that could be listed as "not shown".
    assert "\nmerge took " in merged and "wall time" not in merged
    assert "not merged because" not in merged
    # The report of the store: titled as one, the tables scored as the plots (the robots'
    # sources have ground truth), where they showed ATE "-" beside the plots' errors.
    assert main(["--quiet", "report", str(store)]) == 0
    text = (folder / "report" / "report.html").read_text()
    assert "<h1>fleetslam cloud store store</h1>" in text and "merge took " in text
    assert "no ground truth in the run" not in text and "joint ATE" in text
    robots = json.loads((folder / "summary.json").read_text())["robots"]
    assert not any(r.get("ate") for r in robots)  # summary.json stays the cloud's

"""The view in rerun: the cloud's live view records what it should and never holds up a
session; ``fleetslam view`` opens a finished run; without rerun, a clear error says how to
install it."""

from __future__ import annotations

import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import HANG_S, exact_config, small_scene

from fleetslam.cli import main

N_FRAMES = 16


def entity_paths(rrd) -> set[str]:
    """What rerun's own reader finds in a recording."""
    from rerun.chunk import RrdReader

    return set(RrdReader(str(rrd)).store().schema().entity_paths())


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return small_scene(tmp_path_factory, N_FRAMES)


@pytest.fixture(scope="module")
def viewed_run(scene, tmp_path_factory):
    """Two robots through an in-process cloud with the view recording to a file."""
    pytest.importorskip("rerun")
    from fleetslam.cloud.server import CloudServer
    from fleetslam.datasets.tum import RgbdSequence
    from fleetslam.edge.robot import Robot
    from fleetslam.launch import free_endpoint
    from fleetslam.visualisation.views import open_view

    tmp = tmp_path_factory.mktemp("viewed")
    config, endpoint = exact_config(), free_endpoint()
    view = open_view(config, tmp / "live.rrd", live=False)
    server = CloudServer(config, tmp / "cloud", endpoint, view=view).start()
    try:
        for name, folder in zip(("r0", "r1"), scene):
            Robot(name, RgbdSequence(folder), str(folder), 3, config, endpoint,
                  show_progress=False).run()
        summary = server.merge()
    finally:
        server.close()  # closes the view: the file gets its footer
    return tmp, summary, view


def test_a_cloud_run_with_the_view_saved_loads_back_with_its_entities(viewed_run):
    tmp, summary, view = viewed_run
    paths = entity_paths(tmp / "live.rrd")
    assert view.dropped == 0
    for robot in ("r0", "r1"):
        for entity in ("camera", "trajectory/00000", "keyframe_centres"):
            assert f"/world/{robot}/{entity}" in paths, entity
        # Every keyframe's points, under the keyframe's pose.
        keyframes = {p for p in paths if p.startswith(f"/world/{robot}/keyframes/")
                     and p.endswith("/points")}
        assert len(keyframes) == next(r["keyframes"] for r in summary["robots"]
                                      if r["name"] == robot) >= 2
        for series in ("split_point", "cloud_ms", "link_kB_per_s"):
            assert f"/robots/{robot}/{series}" in paths
    # The two robots film one scene: the merge finds inter-robot constraints, and the view
    # shows them.
    assert summary["merge"]["constraints"]
    assert "/world/constraints" in paths


def test_the_view_logs_every_pose_and_decimated_keyframe_points(viewed_run):
    from rerun.chunk import RrdReader

    tmp, summary, _ = viewed_run
    rows: dict[str, int] = {}
    for line in RrdReader(str(tmp / "live.rrd")).store().summary().splitlines():
        path, _, rest = line.partition(" rows=")
        if rest and "static=False" in rest:
            rows[path] = rows.get(path, 0) + int(rest.split()[0])
    assert rows["/world/r0/camera"] == N_FRAMES  # a pose per tracked frame
    assert rows["/robots/r0/split_point"] == N_FRAMES


def test_fleetslam_view_writes_a_finished_runs_recording(viewed_run, tmp_path, capsys):
    run_dir, summary = viewed_run[0] / "cloud", viewed_run[1]
    out = tmp_path / "run.rrd"
    assert main(["--quiet", "view", str(run_dir), "--save", str(out)]) == 0
    assert f"wrote {out}" in capsys.readouterr().out
    paths = entity_paths(out)
    for robot in ("r0", "r1"):
        assert {f"/world/{robot}/map", f"/world/{robot}/trajectory",
                f"/world/{robot}/camera", f"/world/{robot}/keyframe_centres"} <= paths
    # The merge joined both robots into one global map, which the view shows.
    assert summary["merge"]["components"] == {"r0": ["r0", "r1"]}
    assert (run_dir / "global_map.ply").is_file()
    assert {"/world/global/map", "/world/global/r0", "/world/global/r1"} <= paths


def test_fleetslam_view_of_a_folder_that_is_not_a_run_names_it(tmp_path, capsys):
    (tmp_path / "notes").mkdir()
    assert main(["view", str(tmp_path), "--save", str(tmp_path / "x.rrd")]) == 2
    err = capsys.readouterr().err
    assert f"{tmp_path}: not a fleetslam run folder" in err
    assert main(["view", str(tmp_path / "missing")]) == 2
    assert f"{tmp_path / 'missing'}: no such folder" in capsys.readouterr().err
    assert not (tmp_path / "x.rrd").exists()


def test_without_rerun_the_view_says_how_to_install_it(monkeypatch, tmp_path, capsys):
    monkeypatch.setitem(sys.modules, "rerun", None)  # import rerun fails as if absent
    assert main(["cloud", "--view", "--out", str(tmp_path / "c")]) == 2
    assert "pip install 'fleetslam[view]'" in capsys.readouterr().err
    assert main(["--quiet", "demo", "--frames", "2", "--scene", str(tmp_path / "s"),
                 "--out", str(tmp_path / "d"), "--save", str(tmp_path / "d.rrd")]) == 2
    assert "pip install 'fleetslam[view]'" in capsys.readouterr().err
    assert not (tmp_path / "d").exists()
    # The view off needs no rerun.
    from fleetslam.visualisation.live_view import NullView
    from fleetslam.visualisation.views import open_view

    assert isinstance(open_view(exact_config(), None, False), NullView)


class StalledRecording:
    """A rerun recording whose every log call hangs once ``stall`` is set."""

    def __init__(self) -> None:
        self.stall = threading.Event()
        self.release = threading.Event()
        self.calls = 0

    def log(self, *args, **kwargs) -> None:
        self.calls += 1
        if self.stall.is_set():
            self.release.wait()

    def __getattr__(self, name):
        return lambda *args, **kwargs: None  # set_time, reset_time, flush, disconnect


def test_a_stalled_view_never_holds_up_a_session(scene, tmp_path):
    pytest.importorskip("rerun")
    from test_cloud import K, robot_messages

    from fleetslam.cloud.session.robot_session import RobotSession
    from fleetslam.cloud.session.store import CloudStore
    from fleetslam.transport.protocol import Hello
    from fleetslam.visualisation.live_view import LiveView

    seq, msgs, poses = robot_messages(scene, K)["r0"]
    config = exact_config().with_values({"view.queue_size": 4, "view.close_timeout_s": 0.5})
    recording = StalledRecording()
    view = LiveView(config, recording)
    recording.stall.set()  # the view's thread hangs on its first update from here on
    session = RobotSession.open("r0", Hello(K, seq.camera, "test"), config,
                                CloudStore(tmp_path), lambda key, data: None, view=view)
    view.robot("r0", seq.camera)
    try:
        start = time.monotonic()
        for data in msgs:
            session.submit_frame(data, time.monotonic())
        session.drain(timeout=60.0)
        assert session.counts()["frames"] == N_FRAMES  # every frame tracked ...
        np.testing.assert_array_equal(  # ... exactly as without a view
            np.array([r.T_world_camera for r in session.state.rows]), poses)
        assert view.dropped >= N_FRAMES - config.view.queue_size - 1
        assert time.monotonic() - start < HANG_S
        closing = time.monotonic()
        view.close()  # gives up on the stalled thread after close_timeout_s
        assert time.monotonic() - closing < HANG_S  # not stuck on the stalled thread
    finally:
        recording.release.set()
        session.close()


def test_without_a_display_the_live_view_is_served_for_a_viewer_to_connect(monkeypatch,
                                                                           tmp_path):
    """``--view`` on a headless machine: served over gRPC; rerun's own client, connected to
    the URL, receives what the view logs (here: it records it to a file)."""
    import signal
    import subprocess
    import warnings

    pytest.importorskip("rerun")
    from fleetslam.camera import Camera
    from fleetslam.launch import free_endpoint
    from fleetslam.visualisation import recording
    from fleetslam.visualisation.views import open_view

    viewer_cli = recording._viewer_executable()
    if viewer_cli is None:
        pytest.skip("rerun's viewer executable is not installed")
    monkeypatch.setattr(recording, "can_spawn_viewer", lambda: False)
    port = int(free_endpoint().rsplit(":", 1)[1])
    config = exact_config().with_values({"view.grpc_port": port})
    assert any(recording.grpc_url(config.view) in line
               for line in recording.live_plan(config.view, None, True))
    view = open_view(config, None, live=True)
    out = tmp_path / "received.rrd"
    expected = {"/world/r0/camera", "/robots/r0/split_point"}

    def received_paths(path: Path) -> set[str]:
        from rerun.chunk import RrdReader

        if not path.exists():
            return set()
        with warnings.catch_warnings():  # a file cut short has no footer: read it whole
            warnings.simplefilter("ignore")
            try:
                return set(RrdReader(str(path)).stream().collect().schema().entity_paths())
            except ValueError:  # nothing recorded yet ("No recording store found")
                return set()
    client = subprocess.Popen([viewer_cli, recording.grpc_url(config.view), "--save", str(out),
                               "--port", "auto"], stdin=subprocess.DEVNULL,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        view.robot("r0", Camera(525.0, 525.0, 319.5, 239.5))
        for i in range(5):
            T = np.eye(4)
            T[0, 3] = 0.1 * i
            view.frame("r0", i, T, True, i == 0, 3, 10.0)
        # The client connects (the server keeps what came before) and records what it got;
        # its start-up takes seconds on a loaded machine: wait for it, with a deadline.
        deadline = time.monotonic() + 30.0
        while time.monotonic() < deadline and not expected <= received_paths(out):
            time.sleep(0.5)
        view.close()
        time.sleep(1.0)
    finally:
        client.send_signal(signal.SIGINT)  # it records until stopped
        try:
            client.wait(10)
        except subprocess.TimeoutExpired:
            client.kill()
            client.wait()
    assert expected <= received_paths(out)

"""Every damaged checkpoint is refused the same clean way (a CheckpointError naming the file
and what is wrong), at a bounded cost, before any of it is used; the cloud then keeps the
file aside, serves the robot a fresh session and tells it its history was lost, while the
other robots' sessions are restored as ever."""

from __future__ import annotations

import io
import json
import tracemalloc
import types
import zipfile

import numpy as np
import pytest
from conftest import exact_config
from test_cloud import FakeRobot

from fleetslam.backend.back_end import new_state
from fleetslam.camera import Camera
from fleetslam.cloud.server import CloudServer
from fleetslam.cloud.session.session_state import SessionState, capture
from fleetslam.cloud.session.store import CHECKPOINT, CloudStore
from fleetslam.config import Config
from fleetslam.edge.report import RobotReport
from fleetslam.edge.robot import Robot
from fleetslam.launch import free_endpoint
from fleetslam.transport import protocol
from fleetslam.transport.protocol import Hello
from fleetslam.wire.data_tree import CheckpointError

CAMERA = Camera(525.0, 525.0, 319.5, 239.5)


def _checkpoint(robot: str = "r0") -> bytes:
    """A valid checkpoint: a session as a hello opens it."""
    return capture(SessionState(robot, Hello(3, CAMERA, "test"),
                                new_state(Config(), CAMERA))).to_bytes()


def _parts(blob: bytes) -> tuple[dict, dict[str, np.ndarray]]:
    files = np.load(io.BytesIO(blob), allow_pickle=False)
    arrays = {k: files[k] for k in files.files}
    return json.loads(arrays.pop("__tree__").tobytes()), arrays


def _pack(tree: dict | str, arrays: dict[str, np.ndarray]) -> bytes:
    text = tree if isinstance(tree, str) else json.dumps(tree)
    buffer = io.BytesIO()
    np.savez(buffer, __tree__=np.frombuffer(text.encode(), np.uint8), **arrays)
    return buffer.getvalue()


def _map(tree: dict) -> dict:
    return tree["state"]["attributes"]["tracking"]["attributes"]["map"]["attributes"]


def _wrong_type() -> bytes:
    tree, arrays = _parts(_checkpoint())
    tree["state"]["attributes"]["rows"] = {"__obj__": "Hello", "attributes": {}}
    return _pack(tree, arrays)


def _wrong_shape() -> bytes:
    tree, arrays = _parts(_checkpoint())
    arrays[_map(tree)["xyz"]["__nd__"]] = np.zeros((5, 2))
    return _pack(tree, arrays)


def _index_out_of_range() -> bytes:
    tree, arrays = _parts(_checkpoint())
    lmap = _map(tree)
    arrays[lmap["xyz"]["__nd__"]] = np.zeros((2, 3))
    for name, value in {"descriptors": np.zeros((2, 32), np.uint8), "weight": np.zeros(2),
                        "last_keyframe": np.zeros(2, np.int64),
                        "octave": np.zeros(2, np.int64), "distance": np.zeros(2),
                        "alive": np.ones(2, bool), "first_keyframe": np.zeros(2, np.int64),
                        "n_visible": np.ones(2, np.int64), "n_found": np.ones(2, np.int64),
                        "obs_keyframe": np.zeros(1, np.int64),
                        "obs_landmark": np.array([7]),  # the map has 2 landmarks
                        "obs_uv": np.zeros((1, 2)), "obs_depth": np.ones(1),
                        "obs_octave": np.zeros(1, np.int64)}.items():
        arrays[lmap[name]["__nd__"]] = value
    return _pack(tree, arrays)


def _cut_member() -> bytes:
    """A zip that is whole (its CRCs right) around an .npy member cut short."""
    tree, arrays = _parts(_checkpoint())
    victim = _map(tree)["xyz"]["__nd__"]
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as z:
        z.writestr("__tree__.npy", _npy(json.dumps(tree).encode()))
        for name, array in arrays.items():
            member = io.BytesIO()
            np.save(member, array)
            data = member.getvalue()
            z.writestr(f"{name}.npy", data[:40] if name == victim else data)
    return buffer.getvalue()


def _bad_hello() -> bytes:
    tree, arrays = _parts(_checkpoint())
    tree["state"]["attributes"]["hello"]["attributes"]["offload_at"] = 5
    return _pack(tree, arrays)


def _hiding() -> bytes:
    tree, arrays = _parts(_checkpoint())
    tree["state"]["attributes"]["tracking"]["attributes"]["predict_pose"] = 1
    return _pack(tree, arrays)


def _bad_setting() -> bytes:
    """A value of the checkpoint's own config that a config file could not hold (found by
    bench/fuzz_checkpoint.py: the session restored, then failed at every frame)."""
    tree, arrays = _parts(_checkpoint())
    config = tree["state"]["attributes"]["tracking"]["attributes"]["config"]["attributes"]
    config["tracking"]["attributes"]["local_map_scope"] = "x"
    return _pack(tree, arrays)


def _far_principal_point() -> bytes:
    tree, arrays = _parts(_checkpoint())
    tree["state"]["attributes"]["hello"]["attributes"]["camera"]["attributes"]["cx"] = 1e308
    return _pack(tree, arrays)


def _deep() -> bytes:
    tree, arrays = _parts(_checkpoint())
    text = json.dumps({**tree, "state": None}).replace("null", "[" * 100_000 + "]" * 100_000)
    return _pack(text, arrays)


DAMAGED = {
    "empty": (lambda: b"", "empty file"),
    "an array member cut short": (_cut_member, "array 'a.*': bad .npy header"),
    "deep nesting": (_deep, r"nested 100001 deep \(at most 64\)"),
    "a field of the wrong type": (_wrong_type, r"session\.rows is a Hello, not a list"),
    "an array of the wrong shape": (_wrong_shape, r"map\.xyz has shape \(5, 2\), expected"),
    "an index out of range": (_index_out_of_range, "landmarks outside 0..1"),
    "a hello the wire would refuse": (_bad_hello, "hello: offloading point 5 not supported"),
    "a field hiding a method": (_hiding, r"tracking\.predict_pose would hide BackEndState"),
    "a setting out of its range": (_bad_setting,
                                   "tracking.local_map_scope = 'x': must be one of"),
    "a principal point far outside the image": (_far_principal_point,
                                                "cx must be within 4 image sizes"),
}


@pytest.mark.parametrize("case", list(DAMAGED))
def test_every_damaged_checkpoint_is_refused_naming_the_file_and_why(tmp_path, case):
    make, reason = DAMAGED[case]
    (tmp_path / "r0").mkdir()
    path = tmp_path / "r0" / CHECKPOINT
    path.write_bytes(make())
    with pytest.raises(CheckpointError, match=f"{path}: .*{reason}"):
        CloudStore(tmp_path).load_checkpoint("r0")


@pytest.fixture(scope="module")
def zip_bomb() -> bytes:
    """~1.2 MB that a zip reader inflates to 256 MB: a checkpoint whose session is one array
    of zeros, deflated."""
    tree, _ = _parts(_checkpoint())
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as z:
        z.writestr("__tree__.npy", _npy(json.dumps({**tree, "state": {"__nd__": "a0"}})
                                        .encode()))
        with z.open("a0.npy", "w", force_zip64=True) as member:
            chunk = bytes(1 << 22)
            member.write(_npy_header(64 * len(chunk)))
            for _ in range(64):
                member.write(chunk)
    return buffer.getvalue()


def _npy_header(n: int) -> bytes:
    buffer = io.BytesIO()
    np.lib.format.write_array_header_1_0(buffer, {"descr": "|u1", "fortran_order": False,
                                                  "shape": (n,)})
    return buffer.getvalue()


def _npy(data: bytes) -> bytes:
    return _npy_header(len(data)) + data


def test_a_zip_bomb_is_refused_before_it_is_inflated(tmp_path, zip_bomb):
    assert len(zip_bomb) < 2 << 20
    (tmp_path / "r0").mkdir()
    (tmp_path / "r0" / CHECKPOINT).write_bytes(zip_bomb)
    store = CloudStore(tmp_path)
    tracemalloc.start()
    try:
        with pytest.raises(CheckpointError, match="is compressed"):
            store.load_checkpoint("r0")
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 16 << 20, f"peak {peak / 2**20:.0f} MiB while refusing a 1 MB file"


def test_a_checkpoint_over_the_limit_is_refused_unread(tmp_path):
    (tmp_path / "r0").mkdir()
    (tmp_path / "r0" / CHECKPOINT).write_bytes(_checkpoint())
    with pytest.raises(CheckpointError, match="exceeds the limit of 1000"):
        CloudStore(tmp_path, max_checkpoint_bytes=1000).load_checkpoint("r0")


def test_a_robot_with_a_damaged_checkpoint_gets_a_fresh_session_and_is_told(tmp_path):
    """Through the real restore path: a restarted cloud whose store holds r0's damaged
    checkpoint (deep nesting: a RecursionError once) and r1's good one. r0's hello is
    answered with a fresh session and why its history was lost, the file kept aside; r1
    resumes its session."""
    store = tmp_path / "cloud"
    damaged = _deep()
    for robot, blob in (("r0", damaged), ("r1", _checkpoint("r1"))):
        (store / robot).mkdir(parents=True)
        (store / robot / CHECKPOINT).write_bytes(blob)
    (store / "r0" / "keyframes").mkdir()
    (store / "r0" / "keyframes" / "000003.fskf").write_bytes(b"an old keyframe")
    endpoint = free_endpoint()
    server = CloudServer(exact_config(), store, endpoint).start()
    from fleetslam.transport.zenoh_session import open_connecting

    client = open_connecting(endpoint)
    robots = [FakeRobot(client, r, CAMERA) for r in ("r0", "r1")]
    try:
        welcome = robots[0].hello()
        assert welcome["resumed"] is False and welcome["next_index"] == 0
        assert "nested 100001 deep" in welcome["history_lost"]
        kept = list((store / "r0").glob(f"{CHECKPOINT}.damaged-*"))
        assert [p.read_bytes() for p in kept] == [damaged]  # nothing stored is lost
        assert str(kept[0]) in welcome["history_lost"]
        # Its old keyframes too: the fresh session must not take them for its own.
        assert welcome["keyframes_stored"] == 0
        old = list((store / "r0").glob("keyframes.damaged-*/000003.fskf"))
        assert [p.read_bytes() for p in old] == [b"an old keyframe"]
        other = robots[1].hello()
        assert other["resumed"] is True and "history_lost" not in other
    finally:
        for robot in robots:
            robot.close()
        client.close()
        server.close()


def test_the_robot_logs_and_reports_a_lost_history(caplog):
    reason = "store/r0/session.ckpt: empty file; kept as store/r0/session.ckpt.damaged-x"
    welcome = protocol.Welcome(False, 0, 0, 0, history_lost=reason)
    robot = types.SimpleNamespace(_hello=lambda: welcome, live=None, offload_at=3,
                                  robot_id="r0", report=RobotReport("r0", 3))
    assert Robot._open_session(robot) == (0, 0)
    assert robot.report.history_lost == reason
    assert f"lost this robot's session history and starts a fresh session: {reason}" \
        in caplog.text


def test_a_session_that_fails_to_start_from_its_checkpoint_starts_afresh(tmp_path,
                                                                         monkeypatch):
    """A checkpoint that passes every check yet whose session fails to start (a bug) is
    handled as a damaged one: set aside, and the robot's next hello opens a fresh session
    that says why."""
    from fleetslam.cloud.session.robot_session import RobotSession
    from fleetslam.cloud.session.sessions import SessionTable
    from fleetslam.visualisation.live_view import NullView

    (tmp_path / "r0").mkdir()
    (tmp_path / "r0" / CHECKPOINT).write_bytes(_checkpoint())
    table = SessionTable(exact_config(), CloudStore(tmp_path), lambda key, data: None,
                         NullView())
    started = RobotSession.start

    def start(self):
        raise RuntimeError("a bug")

    monkeypatch.setattr(RobotSession, "start", start)
    assert table.session("r0") is None
    monkeypatch.setattr(RobotSession, "start", started)
    session = table.open("r0", Hello(3, CAMERA, "test"))
    try:
        assert "cannot be restored (RuntimeError('a bug'))" in session.history_lost
        assert list((tmp_path / "r0").glob(f"{CHECKPOINT}.damaged-*"))
    finally:
        session.close()


def test_the_checkpoint_fuzzer_finds_nothing_on_a_few_cases():
    """bench/fuzz_checkpoint.py on 60 cases, so it cannot rot: every family runs, and every
    mutated checkpoint is refused cleanly or restored into a session that tracks."""
    import importlib.util
    import sys

    from conftest import PROJECT, TUM_RPY, require

    require(TUM_RPY)
    spec = importlib.util.spec_from_file_location("fuzz_checkpoint",
                                                  PROJECT / "bench" / "fuzz_checkpoint.py")
    fuzz = importlib.util.module_from_spec(spec)
    sys.modules["fuzz_checkpoint"] = fuzz
    spec.loader.exec_module(fuzz)
    blobs, camera, frame = fuzz.seeds(6, TUM_RPY)
    result = fuzz.fuzz(blobs, camera, frame, 60, seed=7)
    assert all(sum(o.values()) == 12 for o in result["outcomes"].values()), result
    assert result["non_clean"] == 0, result["findings"]


def _within(seconds: float, call) -> object:
    """``call()``'s result, or a failure if it takes longer than ``seconds`` (a hang)."""
    import threading

    result: list = []
    thread = threading.Thread(target=lambda: result.append(call()), daemon=True)
    thread.start()
    thread.join(seconds)
    assert not thread.is_alive(), f"still waiting after {seconds} s"
    return result[0]


def test_a_fifo_or_a_folder_named_as_a_checkpoint_is_refused_at_once(tmp_path):
    """Opening a FIFO to read waits for a writer for ever: a store that holds one where a
    checkpoint (or a keyframe) belongs refuses it as not a regular file, at once."""
    import os

    store = CloudStore(tmp_path)
    (tmp_path / "r0" / "keyframes").mkdir(parents=True)
    os.mkfifo(tmp_path / "r0" / CHECKPOINT)
    os.mkfifo(tmp_path / "r0" / "keyframes" / "000003.fskf")
    (tmp_path / "r1" / CHECKPOINT).mkdir(parents=True)

    def refused(call):
        try:
            call()
        except CheckpointError as exc:
            return exc
        raise AssertionError("not refused")

    for call in (lambda: store.load_checkpoint("r0"), lambda: store.keyframe("r0", 3),
                 lambda: store.load_checkpoint("r1")):
        error = _within(10.0, lambda: refused(call))
        assert "not a regular file" in str(error)


@pytest.mark.parametrize("where", ["behind", "inside"])
def test_a_checkpoint_padded_with_a_sparse_hole_is_refused_unread(tmp_path, where):
    """A real checkpoint with a 256 MB hole (a sparse file: no disk, all of it memory once
    read) behind its directory, or between its members and the directory: the archive's
    own directory (read at the end alone) accounts for a few kB, so it is refused before
    the file is read whole, naming the file."""
    import os

    blob = _checkpoint()
    path = tmp_path / "r0" / CHECKPOINT
    path.parent.mkdir()
    hole = 256 << 20
    if where == "behind":
        path.write_bytes(blob)
        os.truncate(path, len(blob) + hole)
    else:  # the members, a hole, then the directory moved past it (offsets rewritten)
        with zipfile.ZipFile(io.BytesIO(blob)) as archive:
            directory_at = archive.start_dir
        end = blob.rindex(b"PK\x05\x06")
        tail = bytearray(blob[directory_at:])
        moved = directory_at + hole
        at = end - directory_at + 16  # the end record's directory offset
        tail[at:at + 4] = moved.to_bytes(4, "little")
        with open(path, "wb") as f:
            f.write(blob[:directory_at])
            f.seek(moved)
            f.write(tail)
    tracemalloc.start()
    try:
        with pytest.raises(CheckpointError, match=r"not an archive fleetslam wrote|not a zip"
                           ) as error:
            CloudStore(tmp_path).load_checkpoint("r0")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert str(path) in str(error.value)
    assert peak < 16 << 20, peak

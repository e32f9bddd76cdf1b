"""Session checkpoints are data: a restored session tracks on exactly as the original, and
a file that is not a checkpoint of this version (a pickle, another version, a class that is
no part of a session, garbage) is refused with a message naming the file."""

from __future__ import annotations

import io
import json
import pickle

import numpy as np
import pytest

from conftest import small_scene
from fleetslam.backend.robot_slam import RobotSlam
from fleetslam.camera import Camera
from fleetslam.cloud.session.session_state import (CHECKPOINT_CLASSES, SessionState, TrajectoryRow,
                                                   capture)
from fleetslam.cloud.session.store import CloudStore
from fleetslam.config import Config
from fleetslam.datasets.tum import RgbdSequence
from fleetslam.pipeline.states import CapturedFrame
from fleetslam.transport.protocol import Hello
from fleetslam.wire import data_tree


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    seq = RgbdSequence(small_scene(tmp_path_factory, 16)[0])
    return seq.camera, [CapturedFrame(f.index, f.timestamp, f.rgb, f.depth_m) for f in seq]


def test_a_restored_session_tracks_on_exactly_as_the_original(frames, tmp_path):
    camera, captured = frames
    original = RobotSlam.new(Config(), camera)
    rows = []
    for frame in captured[:10]:
        out = original.track(frame)
        rows.append(TrajectoryRow(out.index, out.timestamp, out.T_world_camera, out.tracked,
                                  out.is_keyframe, out.reference_keyframe,
                                  out.T_reference_camera))
    state = SessionState("r0", Hello(3, camera, "test"), original.state,
                         original.front_end, 9, 9, rows)
    store = CloudStore(tmp_path)
    store.save_checkpoint("r0", state)
    assert store.robots_with_checkpoints() == ["r0"]
    restored = store.load_checkpoint("r0")
    assert restored.hello == state.hello and len(restored.rows) == 10
    again = RobotSlam(Config(), camera, front_end=restored.front_end,
                             state=restored.tracking)
    for frame in captured[10:]:
        a, b = original.track(frame), again.track(frame)
        assert a.T_world_camera.tobytes() == b.T_world_camera.tobytes()
        assert a.is_keyframe == b.is_keyframe


def _tree(blob: bytes) -> dict:
    return json.loads(bytes(np.load(io.BytesIO(blob))["__tree__"]).decode())


def _with_tree(tree: dict) -> bytes:
    buffer = io.BytesIO()
    np.savez(buffer, __tree__=np.frombuffer(json.dumps(tree).encode(), np.uint8))
    return buffer.getvalue()


def test_what_is_not_a_checkpoint_of_this_version_is_refused_naming_the_file(tmp_path):
    hello = Hello(3, Camera(525.0, 525.0, 319.5, 239.5), "s")
    tree = _tree(data_tree.dumps(hello, CHECKPOINT_CLASSES))
    assert data_tree.loads(_with_tree(tree), "f", CHECKPOINT_CLASSES, 1 << 20) == hello
    cases = {
        "checkpoint format version 4": {**tree, "version": 4},
        "'Popen' is not part of a session": {**tree, "state": {"__obj__": "Popen",
                                                               "attributes": {}}},
        "not a fleetslam session checkpoint": {"format": "other"},
    }
    for message, bad in cases.items():
        with pytest.raises(ValueError, match=f"where.ckpt: .*{message}"):
            data_tree.loads(_with_tree(bad), "where.ckpt", CHECKPOINT_CLASSES, 1 << 20)
    with pytest.raises(ValueError, match="where.ckpt: not a fleetslam session checkpoint"):
        data_tree.loads(b"garbage", "where.ckpt", CHECKPOINT_CLASSES, 1 << 20)
    with pytest.raises(TypeError, match="cannot be checkpointed"):
        data_tree.dumps(object(), CHECKPOINT_CLASSES)
    # A pickle left by an older version is never loaded.
    (tmp_path / "r0").mkdir()
    (tmp_path / "r0" / "session.pkl").write_bytes(pickle.dumps({"x": 1}))
    with pytest.raises(ValueError, match="session.pkl: a checkpoint pickled by an older"):
        CloudStore(tmp_path).load_checkpoint("r0")


def _session_state(frames, n: int) -> SessionState:
    camera, captured = frames
    pipeline = RobotSlam.new(Config(), camera)
    for frame in captured[:n]:
        pipeline.track(frame)
    return SessionState("r0", Hello(3, camera, "test"), pipeline.state,
                        pipeline.front_end, n - 1, n - 1)


def test_two_writers_of_one_checkpoint_never_break_it(frames, tmp_path):
    """Two workers may for a moment both serve a robot: their writes of its checkpoint must
    never rename or truncate each other's (each file on disk is one whole checkpoint)."""
    import threading

    store = CloudStore(tmp_path)
    blobs = [capture(_session_state(frames, n)) for n in (4, 8)]
    errors = []

    def write(blob) -> None:
        try:
            for _ in range(40):
                store.write_checkpoint("r0", blob)
        except Exception as exc:  # noqa: BLE001 - the test reports any
            errors.append(exc)

    writers = [threading.Thread(target=write, args=(b,)) for b in blobs]
    for w in writers:
        w.start()
    for w in writers:
        w.join()
    assert errors == []
    assert store.load_checkpoint("r0").last_index in (3, 7)
    assert [p.name for p in (tmp_path / "r0").iterdir()] == ["session.ckpt"]


def test_the_merger_gets_a_keyframe_only_once_its_checkpoint_is_on_disk(frames, tmp_path):
    """A worker taking a session over from the store must find every keyframe the merger
    already holds: the keyframe goes to the merger after its checkpoint is written."""
    from fleetslam.cloud.session.robot_session import RobotSession

    store = CloudStore(tmp_path)
    seen = []

    def sink(summary, poses) -> None:
        on_disk = store.load_checkpoint("r0")
        seen.append((summary, on_disk.last_index if on_disk else None))

    session = RobotSession(_session_state(frames, 8), Config(), store, lambda k, d: None,
                           sink).start()
    try:
        keyframe = session.keyframes.newest()
        session.checkpoints.checkpoint(7, keyframe)
        session.checkpoints.checkpoint(7)  # coalesced with the one before: its keyframe still goes
    finally:
        session.close()  # waits for the writer
    assert [(s.keyframe, index) for s, index in seen] == [(keyframe[0].keyframe, 7)]

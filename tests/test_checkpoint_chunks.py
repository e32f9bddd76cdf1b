"""A session checkpoint keeps what never changes (each keyframe's features and landmark
table, each full block of the trajectory) as chunks written once, and the map's and place
database's arrays as logs (a base, then patches): a checkpoint after more tracking carries
only the new chunks and a patch; the restored session tracks on exactly as the original; a
missing, swapped or oversized chunk, or a name that could leave the folder, is refused
naming the file."""

from __future__ import annotations

import json
import re
import shutil

import pytest

from conftest import small_scene
from fleetslam.backend.robot_slam import RobotSlam
from fleetslam.cloud.session import array_log, session_state
from fleetslam.cloud.session.session_state import Chunks, SessionState, TrajectoryRow, capture
from fleetslam.cloud.session.store import CloudStore
from fleetslam.config import Config
from fleetslam.datasets.tum import RgbdSequence
from fleetslam.pipeline.states import CapturedFrame
from fleetslam.transport.protocol import Hello
from fleetslam.wire.data_tree import CheckpointError

BLOCK = 4  # rows per block here (a run's is 256): the short scene fills a few


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    seq = RgbdSequence(small_scene(tmp_path_factory, 16)[0])
    return seq.camera, [CapturedFrame(f.index, f.timestamp, f.rgb, f.depth_m) for f in seq]


@pytest.fixture(autouse=True)
def small_blocks(monkeypatch):
    monkeypatch.setattr(session_state, "ROW_BLOCK", BLOCK)


class Run:
    """A tracking pipeline and the session state a cloud would checkpoint of it."""

    def __init__(self, frames) -> None:
        self.camera, self.captured = frames
        self.pipeline = RobotSlam.new(Config(), self.camera)
        self.rows: list[TrajectoryRow] = []

    def track(self, n: int) -> SessionState:
        for frame in self.captured[len(self.rows):n]:
            out = self.pipeline.track(frame)
            self.rows.append(TrajectoryRow(out.index, out.timestamp, out.T_world_camera,
                                           out.tracked, out.is_keyframe,
                                           out.reference_keyframe, out.T_reference_camera))
        return SessionState("r0", Hello(3, self.camera, "test"), self.pipeline.state,
                            self.pipeline.front_end, n - 1, n - 1, list(self.rows))


def _write(store: CloudStore, chunks: Chunks, state: SessionState):
    blob = capture(state, chunks)
    store.write_checkpoint("r0", blob)
    chunks.confirm(blob)
    return blob


def _names_in_tree(blob) -> set[str]:
    """The chunks a checkpoint's tree names, read from its JSON."""
    return set(re.findall(r'"__chunk__": "([a-z][0-9a-f-]+)"', blob.tree))


def test_only_new_chunks_are_written_and_the_restored_session_tracks_on_exactly(frames,
                                                                                tmp_path):
    run = Run(frames)
    store = CloudStore(tmp_path)
    chunks = Chunks(lambda name: store.has_chunk("r0", name))
    first = _write(store, chunks, run.track(8))
    keyframes = len(run.pipeline.state.map.keyframes)
    assert sum(n.startswith("f") for n in first.chunks) == keyframes
    assert sum(n.startswith("k") for n in first.chunks) == keyframes
    assert sum(n.startswith("r") for n in first.chunks) == 8 // BLOCK
    # The map's and the place database's logs start with a base each.
    assert sum(n.startswith("b") for n in first.chunks) == 2
    # Nothing new: nothing but the changing parts again, and no patch.
    assert capture(run.track(8), chunks).chunks == {}
    state = run.track(10)
    second = _write(store, chunks, state)
    assert not set(second.chunks) & set(first.chunks)
    new_keyframes = len(run.pipeline.state.map.keyframes) - keyframes
    assert sum(n.startswith("f") for n in second.chunks) == new_keyframes
    assert sum(n.startswith("r") for n in second.chunks) == 10 // BLOCK - 8 // BLOCK
    # The map's log a patch or (its patches outweighing the base) a new base; the place
    # database's too if a keyframe was added to it.
    assert sum(n[0] in "bp" for n in second.chunks) == 1 + (new_keyframes > 0)
    assert len(second.tree) < len(capture(state).tree)  # the plain tree holds every row

    restored = store.load_checkpoint("r0")
    assert [(r.index, r.T_world_camera.tobytes()) for r in restored.rows] == \
        [(r.index, r.T_world_camera.tobytes()) for r in state.rows]
    for name in ("descriptors", "owner"):
        assert getattr(restored.tracking.places, name).tobytes() == \
            getattr(state.tracking.places, name).tobytes()
    for name in session_state.LOGGED_ARRAYS[type(state.tracking.map)]:
        assert getattr(restored.tracking.map, name).tobytes() == \
            getattr(state.tracking.map, name).tobytes()
    again = RobotSlam(Config(), run.camera, front_end=restored.front_end,
                             state=restored.tracking)
    for frame in run.captured[10:]:
        a, b = run.pipeline.track(frame), again.track(frame)
        assert a.T_world_camera.tobytes() == b.T_world_camera.tobytes()
        assert a.is_keyframe == b.is_keyframe


def test_replaced_chains_are_deleted_and_the_checkpoint_before_still_loads(frames, tmp_path,
                                                                          monkeypatch):
    monkeypatch.setattr(array_log, "MAX_PATCHES", 2)  # a new base every third checkpoint
    run = Run(frames)
    store = CloudStore(tmp_path)
    chunks = Chunks(lambda name: store.has_chunk("r0", name),
                    lambda names: store.remove_chunks("r0", names))
    folder = tmp_path / "r0"
    bases, before = set(), None
    for n in range(4, 17):
        blob = _write(store, chunks, run.track(n))
        named = _names_in_tree(blob)
        bases |= {name for name in named if name[0] == "b"}
        on_disk = {f.stem for f in (folder / "chunks").iterdir()}
        assert named <= on_disk
        # Two logs, each with at most its current base and the one before on disk.
        assert sum(name[0] == "b" for name in on_disk) <= 4
        restored = store.load_checkpoint("r0")
        assert restored.tracking.map.xyz.tobytes() == run.pipeline.state.map.xyz.tobytes()
        if before is not None:  # a reader that opened the checkpoint before still finds all
            (folder / "before.ckpt").write_bytes(before)
            store.load_checkpoint_file(folder / "before.ckpt")
        before = blob.to_bytes()
    assert len(bases) > 4  # replaced bases were deleted


def test_a_finished_session_keeps_only_the_chunks_of_its_two_newest_checkpoints(
        frames, tmp_path, monkeypatch):
    monkeypatch.setattr(array_log, "MAX_PATCHES", 2)  # a new base every third checkpoint
    run = Run(frames)
    store = CloudStore(tmp_path)
    chunks = Chunks(lambda name: store.has_chunk("r0", name),
                    lambda names: store.remove_chunks("r0", names))
    folder = tmp_path / "r0" / "chunks"
    blobs = [_write(store, chunks, run.track(4))]
    # While the robot runs, a replaced chain waits for the base after next: tracked on until
    # the folder holds chunks neither of the two newest checkpoints names.
    for n in range(5, 15):
        blobs.append(_write(store, chunks, run.track(n)))
        if {f.stem for f in folder.iterdir()} - _names_in_tree(blobs[-1]) \
                - _names_in_tree(blobs[-2]):
            break
    else:
        pytest.fail("no replaced chain waited in the folder")
    state = run.track(n + 1)
    state.ended = True
    last = capture(state, chunks)
    store.write_checkpoint("r0", last, ended=True)
    chunks.confirm(last, ended=True)
    # Read from the trees themselves, not from what the capture says it named.
    assert {f.stem for f in folder.iterdir()} == _names_in_tree(last) | _names_in_tree(blobs[-1])
    # Both checkpoints a store may keep still load, the newest and the one before.
    assert store.load_checkpoint("r0").ended
    (folder.parent / "before.ckpt").write_bytes(blobs[-1].to_bytes())
    store.load_checkpoint_file(folder.parent / "before.ckpt")


def test_a_restored_session_names_the_chunks_it_already_has(frames, tmp_path):
    run = Run(frames)
    store = CloudStore(tmp_path)
    _write(store, Chunks(lambda name: store.has_chunk("r0", name)), run.track(8))
    restored = store.load_checkpoint("r0")
    # A worker taking the session over writes none of them again; its logs start afresh,
    # a base each (its own: a log deletes only the chunks it made).
    again = capture(restored, Chunks(lambda name: store.has_chunk("r0", name))).chunks
    assert sorted(name[0] for name in again) == ["b", "b"]


@pytest.fixture(scope="module")
def template(frames, tmp_path_factory):
    folder = tmp_path_factory.mktemp("template")
    store = CloudStore(folder)
    blob = _write(store, Chunks(lambda name: store.has_chunk("r0", name)), Run(frames).track(8))
    return folder, blob


@pytest.fixture
def written(template, tmp_path):
    """A store with one chunked checkpoint, this test's own copy."""
    folder, blob = template
    shutil.copytree(folder / "r0", tmp_path / "r0")
    return CloudStore(tmp_path), sorted((tmp_path / "r0" / "chunks").iterdir()), blob


def test_a_missing_chunk_is_refused_naming_its_file(written):
    store, files, _ = written
    files[0].unlink()
    with pytest.raises(CheckpointError, match=f"{files[0].name}: missing"):
        store.load_checkpoint("r0")


def test_a_chunk_of_other_content_is_refused(written):
    store, files, _ = written
    features = [f for f in files if f.name.startswith("f")]
    shutil.copy(features[1], features[0])  # a whole chunk, under another's name
    with pytest.raises(CheckpointError, match=f"{features[0].name}: not the chunk its name"):
        store.load_checkpoint("r0")


def test_chunks_count_against_the_checkpoint_limit(written, tmp_path):
    _, _, blob = written
    head = (tmp_path / "r0" / "session.ckpt").stat().st_size
    parts = sum(f.stat().st_size for f in (tmp_path / "r0" / "chunks").iterdir())
    small = CloudStore(tmp_path, max_checkpoint_bytes=head + parts // 2)
    with pytest.raises(CheckpointError, match="exceeds the limit of the checkpoint and its"):
        small.load_checkpoint("r0")


@pytest.mark.parametrize("name", ["../../etc/passwd", "f0000001-zz", "x" * 80, 7])
def test_a_chunk_name_that_is_not_one_is_refused(written, tmp_path, name):
    store, _, blob = written
    tree = json.loads(blob.tree)
    text = json.dumps(tree)
    some = next(iter(blob.chunks))
    bad = json.loads(text.replace(json.dumps(some), json.dumps(name), 1))
    from fleetslam.wire.data_tree import Capture
    store.write_checkpoint("r0", Capture(json.dumps(bad), blob.arrays))
    with pytest.raises(CheckpointError, match="a chunk name that is not one"):
        store.load_checkpoint("r0")

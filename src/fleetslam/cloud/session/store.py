"""What the cloud must not lose: acknowledged keyframes and the tracking checkpoints.

Layout under the cloud's output folder:

    <robot>/keyframes/<frame index>.fskf   KEYFRAME messages as received (checksummed)
    <robot>/session.ckpt                   checkpoint of the robot's cloud session (data:
                                           JSON + arrays, versioned; see session_state.py)
    <robot>/chunks/<name>.chunk            the parts of checkpoints that never change (a
                                           keyframe's features, a block of the trajectory,
                                           the bases and patches of the map's array logs),
                                           named by their content, written once, before
                                           the first checkpoint that names them
    <robot>/session.ckpt.damaged-<time>    a checkpoint that could not be restored and its
    <robot>/keyframes.damaged-<time>       keyframes, kept aside (never deleted) when its
                                           robot started afresh

Every write is atomic and durable (temporary file, fsync, rename, fsync of the folder)
before anyone is told it happened: the cloud acknowledges a keyframe only after this.
"""

from __future__ import annotations

import logging
import os
import re
import threading
import time
from pathlib import Path
from typing import Callable, Iterable

from fleetslam.cloud.session import checkpoint_shape, session_state
from fleetslam.cloud.session.session_state import SessionState
from fleetslam.config import TransportConfig
from fleetslam.io.files import UnreadableFile, Vet, read_regular
from fleetslam.wire import npz_reader
from fleetslam.wire.data_tree import Capture, CheckpointError
from fleetslam.wire.envelope import MAX_PAYLOAD_BYTES

log = logging.getLogger("fleetslam.cloud")

_KEYFRAME_FILE = re.compile(r"^(\d+)\.fskf$")
CHECKPOINT = "session.ckpt"
# What earlier versions wrote: a pickle, which can run code when loaded, so it never is.
OLD_PICKLE_CHECKPOINT = "session.pkl"


class NotOwner(PermissionError):
    """A write refused because the writer does not (or no longer) own the robot (a store
    with owners: coordination/fenced_store.py): an OSError, so a checkpoint writer treats it
    as a write that did not happen."""


def write_durably(path: Path, data: bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    # A temporary name of this writer's own: two writers of one file (two workers for a
    # moment both serving a robot) must never rename or truncate each other's half-file.
    tmp = path.with_name(f"{path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    dir_fd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)


def _read_bounded(path: Path, limit: int, of_what: str,
                  setting: str = "transport.max_checkpoint_bytes", vet: Vet | None = None
                  ) -> bytes:
    """The file's bytes; CheckpointError naming it if it is missing, unreadable, not a
    regular file, over ``limit`` bytes (never more than that is read) or refused by
    ``vet`` before it is read."""
    limit_of = f"the limit {of_what} of" if of_what else "the limit of"
    try:
        return read_regular(path, limit, f"{limit_of} {limit} ({setting})", vet)
    except UnreadableFile as exc:
        raise CheckpointError(exc.where, exc.reason) from None


class CloudStore:
    def __init__(self, root: Path,
                 max_checkpoint_bytes: int = TransportConfig.max_checkpoint_bytes) -> None:
        """``max_checkpoint_bytes``: a larger checkpoint file is refused unread."""
        self.root = Path(root)
        self.root.mkdir(parents=True, exist_ok=True)
        self.max_checkpoint_bytes = max_checkpoint_bytes

    def robot_dir(self, robot_id: str) -> Path:
        return self.root / robot_id

    def keyframe_file(self, robot_id: str, frame_index: int) -> Path:
        return self.robot_dir(robot_id) / "keyframes" / f"{frame_index:06d}.fskf"

    def put_keyframe(self, robot_id: str, frame_index: int, message: bytes) -> None:
        write_durably(self.keyframe_file(robot_id, frame_index), message)

    def has_keyframe(self, robot_id: str, frame_index: int) -> bool:
        return self.keyframe_file(robot_id, frame_index).exists()

    def keyframe(self, robot_id: str, frame_index: int) -> bytes:
        """A stored keyframe message; CheckpointError naming its file if it cannot be read
        (missing, not a regular file, larger than any message the wire takes)."""
        return _read_bounded(self.keyframe_file(robot_id, frame_index), MAX_PAYLOAD_BYTES,
                             "of a message", "the wire's payload limit")

    def keyframe_indices(self, robot_id: str) -> list[int]:
        folder = self.robot_dir(robot_id) / "keyframes"
        if not folder.is_dir():
            return []
        found = (_KEYFRAME_FILE.match(p.name) for p in folder.iterdir())
        return sorted(int(m.group(1)) for m in found if m)

    def _chunk_path(self, robot_id: str, name: str) -> Path:
        return self.robot_dir(robot_id) / "chunks" / f"{name}.chunk"

    def has_chunk(self, robot_id: str, name: str) -> bool:
        return self._chunk_path(robot_id, name).exists()

    def write_chunks(self, robot_id: str, blob: bytes | Capture) -> int:
        """The chunks a checkpoint names that it carries, each written once (the same name,
        the same content: one already there is kept); the bytes written."""
        written = 0
        if isinstance(blob, Capture):
            for name, chunk in blob.chunks.items():
                path = self._chunk_path(robot_id, name)
                if not path.exists():
                    data = chunk.to_bytes()
                    write_durably(path, data)
                    written += len(data)
        return written

    def chunk_files(self, robot_id: str
                    ) -> tuple[Callable[[str], bool], Callable[[Iterable[str]], None]]:
        """What a session's checkpoint chunker (session_state.Chunks) asks of the robot's
        chunk files: whether one exists, and to delete some."""
        return (lambda name: self.has_chunk(robot_id, name),
                lambda names: self.remove_chunks(robot_id, names))

    def remove_chunks(self, robot_id: str, names: Iterable[str]) -> None:
        """Delete chunks no checkpoint names any more (a log's chain its new base replaced,
        cloud/session/array_log.py); one already gone is no error."""
        for name in names:
            try:
                self._chunk_path(robot_id, name).unlink()
            except FileNotFoundError:
                pass
            except OSError as exc:  # disk space not given back, nothing lost
                log.warning("robot %s: chunk %s not deleted: %s", robot_id, name, exc)

    def read_chunk(self, robot_id: str, name: str, limit: int) -> tuple[bytes, str]:
        """A chunk's bytes and its file's name; CheckpointError if it is missing or over
        ``limit`` bytes."""
        path = self._chunk_path(robot_id, name)
        return (_read_bounded(path, limit, "of the checkpoint and its chunks",
                              vet=npz_reader.layout_problem), str(path))

    def save_checkpoint(self, robot_id: str, state: SessionState) -> None:
        self.write_checkpoint(robot_id, session_state.capture(state))

    def write_checkpoint(self, robot_id: str, blob: bytes | Capture, ended: bool = False
                         ) -> int:
        """``ended``: the checkpoint is of a finished robot (this layout keeps it inside the
        checkpoint only; fenced_store.py also tells etcd). The bytes written, its new chunks
        with it."""
        chunks = self.write_chunks(robot_id, blob)
        return chunks + self.write_checkpoint_file(robot_id,
                                                   self.robot_dir(robot_id) / CHECKPOINT, blob)

    def write_checkpoint_file(self, robot_id: str, path: Path, blob: bytes | Capture) -> int:
        """The blob, durably, to ``path`` (its bytes); one over ``max_checkpoint_bytes`` is
        written all the same (the newest state is safer on disk than not), but said."""
        data = blob.to_bytes() if isinstance(blob, Capture) else blob
        if len(data) > self.max_checkpoint_bytes:
            log.error("robot %s: a checkpoint of %d bytes, over transport.max_checkpoint_bytes"
                      " (%d): a restart will not restore it", robot_id, len(data),
                      self.max_checkpoint_bytes)
        write_durably(path, data)
        return len(data)

    def has_checkpoint(self, robot_id: str) -> bool:
        return (self.robot_dir(robot_id) / CHECKPOINT).exists()

    def load_checkpoint(self, robot_id: str) -> SessionState | None:
        """The robot's last checkpoint, None if it has none; CheckpointError naming the file
        and what is wrong if it cannot be restored (damaged, too large, another format
        version, an old pickle), whatever is wrong with it."""
        path = self.robot_dir(robot_id) / CHECKPOINT
        if not path.exists():
            old = self.robot_dir(robot_id) / OLD_PICKLE_CHECKPOINT
            if old.exists():
                raise CheckpointError(str(old), f"a checkpoint pickled by an older fleetslam; "
                                                f"it is never loaded (a pickle can run code). "
                                                f"Move it away to start robot {robot_id}'s "
                                                f"session afresh")
            return None
        return self.load_checkpoint_file(path)

    def load_checkpoint_file(self, path: Path) -> SessionState:
        """The checkpoint in ``path`` (CheckpointError as load_checkpoint, also if there is
        none)."""
        data = _read_bounded(path, self.max_checkpoint_bytes, "", vet=npz_reader.layout_problem)
        robot_id = path.parent.name
        state = session_state.load(data, str(path), self.max_checkpoint_bytes,
                                   lambda name, limit: self.read_chunk(robot_id, name, limit))
        return checkpoint_shape.check(state, str(path))

    def set_aside(self, robot_id: str) -> list[Path]:
        """Move the robot's checkpoint and keyframes out of the way (the checkpoint could
        not be restored; its robot starts afresh, and a fresh session must not take the old
        keyframes for its own): kept as ``session.ckpt.damaged-<UTC time>`` and
        ``keyframes.damaged-<UTC time>``, never deleted. Where they went."""
        folder = self.robot_dir(robot_id)
        stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
        n = 1
        while any(folder.glob(f"*.damaged-{stamp}")):  # twice in a second: never over one
            n += 1
            stamp = f"{time.strftime('%Y%m%dT%H%M%SZ', time.gmtime())}-{n}"
        moved = []
        for name in (CHECKPOINT, "keyframes", "chunks"):
            aside = folder / f"{name}.damaged-{stamp}"
            try:
                os.rename(folder / name, aside)
            except FileNotFoundError:
                continue
            moved.append(aside)
        return moved

    def robots_with_checkpoints(self) -> list[str]:
        return sorted(p.parent.name for p in self.root.glob(f"*/{CHECKPOINT}"))

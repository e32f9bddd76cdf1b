"""What the cloud must not lose: acknowledged keyframes and the tracking checkpoints.

Layout under the cloud's output folder:

    <robot>/keyframes/<frame index>.fskf   KEYFRAME messages as received (checksummed)
    <robot>/session.ckpt                   checkpoint of the robot's cloud session (data:
                                           JSON + arrays, versioned; see session_state.py)

Every write is atomic and durable (temporary file, fsync, rename, fsync of the folder)
before anyone is told it happened: the cloud acknowledges a keyframe only after this.
"""

from __future__ import annotations

import os
import re
import threading
from pathlib import Path
from fleetslam.cloud import session_state
from fleetslam.cloud.session_state import SessionState
from fleetslam.wire.data_tree import Capture

_KEYFRAME_FILE = re.compile(r"^(\d+)\.fskf$")
CHECKPOINT = "session.ckpt"
# What earlier versions wrote: a pickle, which can run code when loaded, so it never is.
OLD_PICKLE_CHECKPOINT = "session.pkl"


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


class CloudStore:
    def __init__(self, root: Path) -> None:
        self.root = Path(root)
        self.root.mkdir(parents=True, exist_ok=True)

    def robot_dir(self, robot_id: str) -> Path:
        return self.root / robot_id

    def _keyframe_path(self, robot_id: str, frame_index: int) -> Path:
        return self.robot_dir(robot_id) / "keyframes" / f"{frame_index:06d}.fskf"

    def put_keyframe(self, robot_id: str, frame_index: int, message: bytes) -> None:
        write_durably(self._keyframe_path(robot_id, frame_index), message)

    def has_keyframe(self, robot_id: str, frame_index: int) -> bool:
        return self._keyframe_path(robot_id, frame_index).exists()

    def keyframe(self, robot_id: str, frame_index: int) -> bytes:
        return self._keyframe_path(robot_id, frame_index).read_bytes()

    def keyframe_indices(self, robot_id: str) -> list[int]:
        folder = self.robot_dir(robot_id) / "keyframes"
        if not folder.is_dir():
            return []
        found = (_KEYFRAME_FILE.match(p.name) for p in folder.iterdir())
        return sorted(int(m.group(1)) for m in found if m)

    def save_checkpoint(self, robot_id: str, state: SessionState) -> None:
        self.write_checkpoint(robot_id, session_state.capture(state))

    def write_checkpoint(self, robot_id: str, blob: bytes | Capture) -> None:
        data = blob.to_bytes() if isinstance(blob, Capture) else blob
        write_durably(self.robot_dir(robot_id) / CHECKPOINT, data)

    def has_checkpoint(self, robot_id: str) -> bool:
        return (self.robot_dir(robot_id) / CHECKPOINT).exists()

    def load_checkpoint(self, robot_id: str) -> SessionState | None:
        """The robot's last checkpoint, None if it has none; ValueError naming the file if
        it cannot be restored (damaged, another format version, an old pickle)."""
        path = self.robot_dir(robot_id) / CHECKPOINT
        if not path.exists():
            old = self.robot_dir(robot_id) / OLD_PICKLE_CHECKPOINT
            if old.exists():
                raise ValueError(f"{old}: a checkpoint pickled by an older fleetslam; it is "
                                 f"never loaded (a pickle can run code). Move it away to "
                                 f"start robot {robot_id}'s session afresh")
            return None
        return session_state.load(path.read_bytes(), str(path))

    def robots_with_checkpoints(self) -> list[str]:
        return sorted(p.parent.name for p in self.root.glob(f"*/{CHECKPOINT}"))

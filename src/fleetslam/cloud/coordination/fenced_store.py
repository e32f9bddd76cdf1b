"""The store for many workers: checkpoints a stale owner writes can never become current.

Beside ``store.py`` (whose single-process layout and behaviour it keeps for keyframes):

    <robot>/session.<epoch>.<seq>.ckpt   immutable checkpoint blobs, named by the writer's
                                         epoch (ownership.py) and its own sequence number

and in etcd, ``<prefix>current/<robot>`` = the checkpoint readers load
(``{"epoch", "seq", "file", "ended", "worker"}``), ``<prefix>ended/<robot>`` once the robot
has finished. A blob is written first; the pointer moves to it only in a transaction
conditioned on the robot's owner key still having the writer's epoch and lease, and, for an
unfinished checkpoint, on the robot not having ended. So a worker fenced meanwhile (or one
cut off and healed) has its write refused, its blob is removed, and the pointer stays; and a
finished robot stays finished whoever writes later.

A write refused is a :class:`NotOwner` (an OSError: a checkpoint writer counts it as a write
that did not happen, and acknowledges nothing it covered).
"""

from __future__ import annotations

import json
import logging
import os
import re
import threading
import time
from collections import deque
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Iterator

from fleetslam.cloud.coordination.coordination_service import EtcdService
from fleetslam.cloud.coordination.etcd_gateway import (EtcdClient, EtcdError, compare, delete_op,
                                                       put_op, range_op)
from fleetslam.cloud.coordination.ownership import Ownership
from fleetslam.cloud.session import session_state
from fleetslam.cloud.session.session_state import KEPT_CHECKPOINTS, SessionState
from fleetslam.cloud.session.store import CloudStore, NotOwner
from fleetslam.config import TransportConfig
from fleetslam.wire.data_tree import Capture, CheckpointError

log = logging.getLogger("fleetslam.cloud")

# Re-reads of the pointer when the blob it named is gone (it moved on meanwhile), or when
# the folder holds a newer blob (its writer puts the blob, then moves the pointer: a reader
# between the two sees the pointer behind for a moment), this long apart.
READ_ATTEMPTS = 3
REREAD_S = 0.05


@dataclass(frozen=True)
class Pointer:
    epoch: int
    seq: int
    file: str
    ended: bool
    worker: str

    @staticmethod
    def parse(value: bytes, where: str) -> "Pointer":
        try:
            d = json.loads(value)
            pointer = Pointer(int(d["epoch"]), int(d["seq"]), str(d["file"]), bool(d["ended"]),
                              str(d["worker"]))
        except (ValueError, KeyError, TypeError) as exc:
            raise CheckpointError(where, f"the checkpoint pointer is not one ({exc!r})") from None
        if "/" in pointer.file or not pointer.file.endswith(".ckpt"):
            raise CheckpointError(where, f"the pointer names {pointer.file!r}, not a checkpoint "
                                         f"file of the robot's folder")
        return pointer


# A checkpoint blob: session.<epoch>.<seq>.ckpt in the store's first coordination era,
# session.<era>-<epoch>.<seq>.ckpt after (etcd_era).
_BLOB = re.compile(r"^session\.(?:(\d+)-)?(\d+)\.(\d+)\.ckpt$")
# Where the store keeps the eras: one file per etcd history it has been written under.
ERAS = "coordination"


def blob_order(name: str) -> tuple[int, int, int] | None:
    """(era, epoch, seq) of a checkpoint blob's name, None for another file."""
    m = _BLOB.match(name)
    return None if m is None else (int(m.group(1) or 0), int(m.group(2)), int(m.group(3)))


def newest_blob(folder: Path) -> tuple[int, int, int, str] | None:
    """(era, epoch, seq, file name) of the newest checkpoint blob of a robot's folder."""
    try:
        names = os.listdir(folder)
    except OSError:
        return None
    found = [(*order, name) for name in names if (order := blob_order(name)) is not None]
    return max(found) if found else None


def etcd_era(root: Path, cluster_id: str) -> int:
    """The store's era for the etcd history ``cluster_id``: 0 for the first it was written
    under, one more for each new one after (an etcd wiped and started again gives epochs
    from 1 again: without eras its blobs would take the names of older ones). Each era is
    a file made exclusively, so workers meeting a new history at once agree."""
    folder = root / ERAS
    folder.mkdir(parents=True, exist_ok=True)
    while True:
        eras = {}
        for name in os.listdir(folder):
            era, _, cluster = name.partition(".")
            if era.isdigit() and cluster:
                eras[cluster] = int(era)
        if cluster_id in eras:
            return eras[cluster_id]
        era = max(eras.values(), default=-1) + 1
        try:
            fd = os.open(folder / f"{era}.{cluster_id}", os.O_CREAT | os.O_EXCL | os.O_WRONLY)
        except FileExistsError:
            continue  # another worker took this number meanwhile: read again
        os.close(fd)
        if era:
            log.error("etcd's history was reset (cluster %s is new to the store %s): its "
                      "checkpoints from now on are era %d, never over the older ones", cluster_id,
                      root, era)
        return era


class CoordinationUnavailable(ConnectionError):
    """etcd could not be asked: the checkpoint is not current (an OSError, like NotOwner)."""


class FencedStore(CloudStore):
    def __init__(self, root: Path, ownership: Ownership,
                 max_checkpoint_bytes: int = TransportConfig.max_checkpoint_bytes) -> None:
        super().__init__(root, max_checkpoint_bytes)
        self.ownership = ownership
        self.client = ownership.client
        self.keys = ownership.keys
        self._lock = threading.Lock()
        self._seq: dict[tuple[str, int], int] = {}
        self._eras: dict[str, int] = {}  # etcd cluster id -> the store's era of it
        self._written: dict[str, deque[Path]] = {}
        self.refused = 0

    # -- writing --------------------------------------------------------------------------------

    def save_checkpoint(self, robot_id: str, state: SessionState) -> None:
        self.write_checkpoint(robot_id, session_state.capture(state), ended=state.ended)

    def write_checkpoint(self, robot_id: str, blob: bytes | Capture, ended: bool = False
                         ) -> int:
        """Write the blob and make it the robot's current checkpoint (the bytes written);
        NotOwner if this worker does not own the robot with a live lease (or the robot has
        ended and this one has not), CoordinationUnavailable if etcd cannot be asked. Either
        way nothing changed."""
        held = self.ownership.holding(robot_id)
        if held is None:
            self.refused += 1
            raise NotOwner(f"robot {robot_id}: worker {self.ownership.worker_id} does not own "
                           f"it (never granted, released or fenced): checkpoint refused")
        return self.write_as(robot_id, blob, *held, ended=ended)

    def write_as(self, robot_id: str, blob: bytes | Capture, epoch: int, lease: int,
                 ended: bool = False) -> int:
        """The write of a worker that was granted ``robot_id`` with ``epoch`` under ``lease``,
        whatever it believes now (a worker paused past its own fence still gets here): etcd
        decides, in one transaction. NotOwner / CoordinationUnavailable as write_checkpoint."""
        era = self._era()
        with self._lock:
            seq = self._seq.get((robot_id, epoch), 0) + 1
            self._seq[(robot_id, epoch)] = seq
        name = f"session.{era}-{epoch}.{seq:06d}.ckpt" if era else \
            f"session.{epoch}.{seq:06d}.ckpt"
        path = self.robot_dir(robot_id) / name
        if path.exists():  # never over a stored checkpoint, whatever etcd says
            raise NotOwner(f"robot {robot_id}: {path} exists already (etcd's epoch {epoch} "
                           f"was used before): checkpoint refused")
        # Chunks are named by content: a stale writer's are the same files, never wrong.
        written = self.write_chunks(robot_id, blob)
        written += self.write_checkpoint_file(robot_id, path, blob)
        owner = self.keys.owner(robot_id)
        pointer = Pointer(epoch, seq, name, ended, self.ownership.worker_id)
        compares = [compare(owner, "CREATE", epoch), compare(owner, "LEASE", lease)]
        success = [put_op(self.keys.current(robot_id), json.dumps(asdict(pointer)))]
        if ended:
            success.append(put_op(self.keys.ended(robot_id), str(epoch)))
        else:  # a finished robot is never turned back into an unfinished one
            compares.append(compare(self.keys.ended(robot_id), "CREATE", 0))
        try:
            result = self.client.txn(compares, success,
                                     [range_op(owner), range_op(self.keys.ended(robot_id))])
        except EtcdError as exc:
            self._drop(path)
            raise CoordinationUnavailable(f"robot {robot_id}: checkpoint epoch {epoch} not made"
                                          f" current ({exc})") from None
        if not result.succeeded:
            self._drop(path)
            self.refused += 1
            owners, ends = result.ranged(0), result.ranged(1)
            if owners and owners[0].create_revision == epoch and owners[0].lease == lease:
                why = "the robot has ended and this checkpoint has not"
            elif owners:
                why = (f"its owner is now {owners[0].value.decode()} epoch "
                       f"{owners[0].create_revision}")
            else:
                why = "it has no owner now"
            log.warning("robot %s: checkpoint of worker %s epoch %d refused: %s%s", robot_id,
                        self.ownership.worker_id, epoch, why, " (ended)" if ends else "")
            if not owners or owners[0].create_revision != epoch or owners[0].lease != lease:
                self.ownership.lost(robot_id, epoch, why)
            raise NotOwner(f"robot {robot_id}: checkpoint of epoch {epoch} refused: {why}")
        self._keep_few(robot_id, path)
        return written

    def _era(self) -> int:
        """This store's era of the etcd history the worker talks to now."""
        cluster = self.client.cluster_id or self.client.cluster()
        with self._lock:
            if self._eras.get(cluster) is None:
                self._eras[cluster] = etcd_era(self.root, cluster)
            return self._eras[cluster]

    def _drop(self, path: Path) -> None:
        # Never current, and never to be: a stale blob left behind would only mislead.
        try:
            os.unlink(path)
        except OSError:
            pass

    def _keep_few(self, robot_id: str, path: Path) -> None:
        with self._lock:
            written = self._written.setdefault(robot_id, deque())
            written.append(path)
            old = [written.popleft() for _ in range(max(0, len(written) - KEPT_CHECKPOINTS))]
        for p in old:
            self._drop(p)

    # -- reading --------------------------------------------------------------------------------

    def current(self, robot_id: str) -> Pointer | None:
        """The robot's current checkpoint as etcd has it (None: none yet)."""
        kv = self.client.get(self.keys.current(robot_id))
        if kv is None:
            return None
        return Pointer.parse(kv.value, f"etcd {self.keys.current(robot_id)}")

    def has_checkpoint(self, robot_id: str) -> bool:
        return self.current(robot_id) is not None

    def load_checkpoint(self, robot_id: str) -> SessionState | None:
        """The checkpoint the pointer names (None: none); CheckpointError as CloudStore's.
        A pointer is not trusted blindly: one behind the newest checkpoint blob of the
        robot's folder (rolled back), or naming a file that is not there, is said and the
        newest blob restored instead, never a fresh session over acknowledged keyframes."""
        folder = self.robot_dir(robot_id)
        for attempt in range(READ_ATTEMPTS):
            pointer = self.current(robot_id)
            newest = newest_blob(folder)
            if pointer is None:
                if newest is None:
                    return None
                log.error("robot %s: etcd names no checkpoint, yet its folder holds some "
                          "(etcd's history reset, or the pointer deleted): restoring the "
                          "newest (%s)", robot_id, newest[3])
                return self.load_checkpoint_file(folder / newest[3])
            named = blob_order(pointer.file)
            if newest is not None and named is not None and newest[:3] > named:
                if attempt + 1 < READ_ATTEMPTS:
                    time.sleep(REREAD_S)  # its writer may be about to move it
                    continue
                log.error("robot %s: etcd's current checkpoint (%s) is behind the newest on "
                          "disk (%s): a rolled-back pointer is not trusted; restoring the "
                          "newest", robot_id, pointer.file, newest[3])
                return self.load_checkpoint_file(folder / newest[3])
            path = folder / pointer.file
            if path.exists():
                return self.load_checkpoint_file(path)
            # Gone: the pointer has moved on since it was read (its writer keeps two), or it
            # names a file that never was; the pointer, read again, says which.
        if newest is not None:
            log.error("robot %s: etcd's current checkpoint names %s, which is not there: not "
                      "trusted; restoring the newest on disk (%s)", robot_id, pointer.file,
                      newest[3])
            return self.load_checkpoint_file(folder / newest[3])
        raise CheckpointError(str(path), "the current checkpoint's file is missing")

    def unfenced_checkpoints(self) -> list[str]:
        """Robots with a checkpoint of the plain layout (``session.ckpt``, written without a
        coordination service) and none named in etcd: this store never reads those."""
        named = set(self.robots_with_checkpoints())
        return [r for r in super().robots_with_checkpoints() if r not in named]

    def robots_with_checkpoints(self) -> list[str]:
        """The robots etcd names a checkpoint of, and those whose folder holds checkpoint
        blobs (etcd's history reset loses the pointers, not the checkpoints)."""
        prefix = self.keys.currents()
        named = {kv.key.decode()[len(prefix):] for kv in self.client.get_prefix(prefix)}
        on_disk = {p.parent.name for p in self.root.glob("*/session.*.ckpt")
                   if blob_order(p.name) is not None}
        return sorted(named | on_disk)

    def set_aside(self, robot_id: str) -> list[Path]:
        """As CloudStore's (the current blob and the keyframes moved aside, kept), and the
        pointer deleted: only by the robot's owner (NotOwner otherwise, nothing moved)."""
        held = self.ownership.holding(robot_id)
        pointer = self.current(robot_id)
        if held is None:
            raise NotOwner(f"robot {robot_id}: worker {self.ownership.worker_id} does not own "
                           f"it: its checkpoint is not set aside")
        epoch, lease = held
        owner = self.keys.owner(robot_id)
        result = self.client.txn([compare(owner, "CREATE", epoch), compare(owner, "LEASE", lease)],
                                 [delete_op(self.keys.current(robot_id))])
        if not result.succeeded:
            raise NotOwner(f"robot {robot_id}: epoch {epoch} is no longer its owner's: its "
                           f"checkpoint is not set aside")
        folder = self.robot_dir(robot_id)
        moved = super().set_aside(robot_id)  # the keyframes (no session.ckpt in this layout)
        if pointer is not None and (folder / pointer.file).exists():
            aside = folder / f"{pointer.file}.damaged"
            os.rename(folder / pointer.file, aside)
            moved.append(aside)
        return moved


@contextmanager
def stored_run(out_dir: Path, etcd_endpoint: str | None = None) -> Iterator[CloudStore]:
    """A run's store to read after the run (benchmarks, tests): with a coordination service,
    the checkpoints etcd names current, through ``etcd_endpoint`` or, when the run's own etcd
    has stopped, an etcd started again on its data (``<out>/etcd``, as ``demo --workers``
    leaves it) for as long as the block runs; else the plain layout."""
    data = Path(out_dir) / "etcd"
    if etcd_endpoint is None and not data.is_dir():
        yield CloudStore(out_dir)
        return
    service = None if etcd_endpoint else EtcdService(data).start()
    try:
        reader = Ownership(EtcdClient(etcd_endpoint or service.endpoint), "reader", 2)
        yield FencedStore(out_dir, reader)
    finally:
        if service is not None:
            service.stop()

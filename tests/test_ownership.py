"""Robot ownership through a real etcd (cloud/coordination/ownership.py) and the store that refuses
stale writers (cloud/coordination/fenced_store.py): two workers (two clients in this process, one of
them talking to etcd through a link the test cuts) compete for robots; grants carry increasing
epochs and never overlap in time; a cut-off worker fences itself before etcd can grant its robot to
the other; its later writes never become current; a finished robot stays finished. Also the service
helper (cloud/coordination/coordination_service.py) that starts etcd for a run."""

from __future__ import annotations

import logging
import threading
import time
from contextlib import contextmanager

import pytest
from conftest import HANG_S, wait_for
from link_cutter import LinkCutter

from fleetslam.backend.back_end import new_state
from fleetslam.camera import Camera
from fleetslam.cloud.coordination.coordination_service import (CoordinationServiceError,
                                                               EtcdService, etcd_binary)
from fleetslam.cloud.coordination.etcd_gateway import EtcdClient
from fleetslam.cloud.coordination.fenced_store import FencedStore
from fleetslam.cloud.coordination.ownership import MERGER, Keys, Ownership, StaleCounts
from fleetslam.cloud.session.session_state import SessionState
from fleetslam.cloud.session.store import NotOwner
from fleetslam.config import Config, PlacementConfig
from fleetslam.transport.protocol import Hello

pytestmark = pytest.mark.skipif(
    etcd_binary() is None,
    reason="the etcd program is not installed (scripts/setup-system.sh installs etcd-server)")

CAMERA = Camera(525.0, 525.0, 319.5, 239.5)
LEASE_S = PlacementConfig.lease_s


def _worker(endpoint: str, name: str, keys: Keys, fenced: list | None = None) -> Ownership:
    on_fenced = None if fenced is None else (lambda robots: fenced.append(
        (time.monotonic(), robots)))
    return Ownership(EtcdClient(endpoint), name, LEASE_S, on_fenced, keys).start()


def _state(last_index: int, ended: bool = False) -> SessionState:
    state = SessionState("r1", Hello(3, CAMERA, "test"), new_state(Config(), CAMERA))
    state.last_index, state.ended = last_index, ended
    return state


# -- the service ----------------------------------------------------------------------------

def test_the_service_starts_healthy_on_loopback_and_stops(tmp_path):
    service = EtcdService(tmp_path / "run" / "etcd").start()
    try:
        assert service.endpoint.startswith("http://127.0.0.1:")
        pid = service.pid
        client = EtcdClient(service.endpoint)
        client.put("k", "v")
        assert client.get("k").value == b"v"
        assert (tmp_path / "run" / "etcd").is_dir()  # its data under the run's folder
    finally:
        service.stop()
    assert service.pid is None
    with pytest.raises(ProcessLookupError):
        import os
        os.kill(pid, 0)


def test_the_service_says_why_it_did_not_start(tmp_path):
    with pytest.raises(CoordinationServiceError, match="not on PATH: install it with scripts"):
        EtcdService(tmp_path / "etcd", binary="etcd-not-installed-here").start()
    # No etcd is healthy within a millisecond: the deadline names itself and the log.
    started = time.monotonic()
    with pytest.raises(CoordinationServiceError, match=r"not healthy within 0.001 s.*etcd.log"):
        EtcdService(tmp_path / "slow" / "etcd", start_deadline_s=0.001).start()
    assert time.monotonic() - started < HANG_S
    # A data folder that is a file: etcd exits, and the error quotes its log.
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "etcd").write_text("not a folder")
    with pytest.raises(CoordinationServiceError, match="etcd exited with status"):
        EtcdService(tmp_path / "bad" / "etcd").start()


def test_a_tls_etcd_serves_the_labs_workers_and_no_one_else(tmp_path):
    """etcd as docs/deployment.md starts it, with `fleetslam certs`' material: mutual TLS.
    The workers' certificate reads and writes; plain http, https without a certificate, and
    a robot's certificate of the lab (another CA) are refused before any key is touched."""
    import ssl
    import urllib.request

    from fleetslam.cloud.coordination.etcd_gateway import EtcdError, EtcdTls
    from fleetslam.transport.certs import make_lab

    lab = make_lab(tmp_path / "lab", ["localhost", "127.0.0.1"], ["r1"])
    service = EtcdService(tmp_path / "run" / "etcd", certs=lab["etcd"]).start()
    try:
        assert service.endpoint.startswith("https://127.0.0.1:")
        worker = EtcdClient(service.endpoint, tls=EtcdTls.from_folder(lab["etcd"]))
        worker.put("fleet/owner/r1", "w1")
        assert worker.get("fleet/owner/r1").value == b"w1"
        plain = EtcdClient(service.endpoint.replace("https", "http"))
        with pytest.raises(EtcdError):
            plain.put("fleet/owner/r1", "attacker")
        anonymous = ssl.create_default_context(cafile=str(lab["etcd"] / "ca.pem"))
        robot = ssl.create_default_context(cafile=str(lab["etcd"] / "ca.pem"))
        robot.load_cert_chain(str(tmp_path / "lab" / "r1.pem"), str(tmp_path / "lab" / "r1.key"))
        for context in (anonymous, robot):
            request = urllib.request.Request(f"{service.endpoint}/v3/kv/put", method="POST",
                                             data=b'{"key": "Zm9v", "value": "YmFy"}')
            with pytest.raises((ssl.SSLError, OSError)):
                with urllib.request.urlopen(request, timeout=5, context=context) as reply:
                    reply.read()
        assert worker.get("foo") is None and worker.get("fleet/owner/r1").value == b"w1"
    finally:
        service.stop()
    with pytest.raises(ValueError, match="https needs the coordination service's"):
        EtcdClient("https://127.0.0.1:2379")
    with pytest.raises(ValueError, match="not the coordination service's TLS folder"):
        EtcdTls.from_folder(tmp_path / "lab")


# -- ownership ----------------------------------------------------------------------------

def test_two_workers_competing_get_one_owner_and_increasing_epochs(etcd, keys):
    a, b = _worker(etcd.endpoint, "wa", keys), _worker(etcd.endpoint, "wb", keys)
    try:
        epochs: list[int] = []
        for robot in ("r1", "r2", "r3", MERGER):  # the merger is granted as a robot is
            results: dict[str, int | None] = {}
            go = threading.Barrier(2)

            def bid(worker: Ownership) -> None:
                go.wait(5.0)
                results[worker.worker_id] = worker.grant(robot)

            threads = [threading.Thread(target=bid, args=(w,)) for w in (a, b)]
            for t in threads:
                t.start()
            for t in threads:
                t.join(5.0)
            won = [w for w, e in results.items() if e is not None]
            assert len(won) == 1, results
            owner = a.owner(robot)
            assert owner is not None and owner.worker == won[0]
            assert owner.epoch == results[won[0]]
            epochs.append(owner.epoch)
            # Handed over: the other worker's grant has a larger epoch.
            winner, loser = (a, b) if won[0] == "wa" else (b, a)
            assert loser.grant(robot) is None
            assert winner.release(robot, owner.epoch)
            again = loser.grant(robot)
            assert again is not None and again > owner.epoch
            epochs.append(again)
            assert winner.release(robot, owner.epoch) is False  # not its grant any more
        assert epochs == sorted(epochs) and len(set(epochs)) == len(epochs)
        # A grant whose answer was lost (asked again): the worker's own key is adopted, not
        # left owned and unserved while its lease lives.
        epoch = a.grant("r9")
        a._mine.pop("r9")
        assert a.grant("r9") == epoch and b.grant("r9") is None
    finally:
        a.close()
        b.close()


def test_two_workers_deciding_on_the_same_owner_table_take_one_robot_between_them(etcd, keys):
    """Both read the owner table, both rank themselves first for a different new robot: the
    first grant is written, the second is refused as decided on stale counts (and is
    written once decided again on the table that has the first), so no worker takes robots
    on counts another's grant has changed."""
    a, b = _worker(etcd.endpoint, "wa", keys), _worker(etcd.endpoint, "wb", keys)
    try:
        seen_a, seen_b = a.owners(), b.owners()
        assert seen_a.workers == {} and seen_a.counts() == {}
        assert a.grant("r1", basis=seen_a.revision) is not None
        with pytest.raises(StaleCounts):
            b.grant("r2", basis=seen_b.revision)
        assert b.owner("r2") is None and "r2" not in b.robots()
        again = b.owners()
        assert again.counts() == {"wa": 1} and again.latest > seen_b.latest
        assert b.grant("r2", basis=again.revision) is not None
        # A release is no grant: counts decided before it still hold.
        table = a.owners()
        assert a.release("r1", a.robots()["r1"])
        assert a.grant("r3", basis=table.revision) is not None
        # The robot itself taken meanwhile: no owner for this worker, not stale counts.
        assert a.grant("r2", basis=a.owners().revision) is None
    finally:
        a.close()
        b.close()


def test_a_cut_off_worker_is_fenced_before_the_other_is_granted(etcd, keys, tmp_path, caplog):
    """Worker A loses etcd (its link cut; etcd and worker B go on). A stops serving before its
    lease can expire; B is granted the robot after the expiry with a larger epoch; healed, A's
    checkpoint writes are refused and the pointer stays B's. Prints the failover time."""
    caplog.set_level(logging.INFO, logger="fleetslam")
    link = LinkCutter(etcd.client_port)
    fenced: list = []
    a = _worker(link.endpoint, "wa", keys, fenced)
    b = _worker(etcd.endpoint, "wb", keys)
    store_a = FencedStore(tmp_path / "store", a)
    store_b = FencedStore(tmp_path / "store", b)
    try:
        epoch_a, old_lease = a.grant("r1"), a.lease
        assert epoch_a is not None
        store_a.save_checkpoint("r1", _state(10))
        assert store_a.current("r1").epoch == epoch_a
        time.sleep(LEASE_S / 3 * 1.5)  # past a renewal or two: the cut falls mid-lease

        cut = time.monotonic()
        link.cut()
        epoch_b = None
        while epoch_b is None:  # B asks as a worker would when the owner is gone
            assert time.monotonic() - cut < HANG_S, "B was never granted r1"
            epoch_b = b.grant("r1")
            granted = time.monotonic()
            if epoch_b is None:
                time.sleep(0.02)
        assert fenced, "A never fenced itself"
        fence_at, robots = fenced[0]
        assert robots == [("r1", epoch_a)]
        # A's every check (epoch, holding) says no from its deadline on, whatever its
        # lease thread does; the callback comes at that deadline.
        assert a._valid_until < granted and fence_at < granted, "two owners overlapped"
        assert epoch_b > epoch_a
        assert a.epoch("r1") is None and not a.live()
        print(f"\nfailover (lease_s {LEASE_S}): cut -> B granted {granted - cut:.2f} s; "
              f"A fenced at +{fence_at - cut:.2f} s, {granted - fence_at:.2f} s before B's "
              f"grant")

        store_b.save_checkpoint("r1", _state(20))
        pointer = store_b.current("r1")
        assert (pointer.epoch, pointer.worker) == (epoch_b, "wb")

        link.heal()
        # A knows it is fenced: refused before anything is written.
        with pytest.raises(NotOwner, match="does not own"):
            store_a.save_checkpoint("r1", _state(30))
        # A paused past its own fence (it still believes its grant): etcd refuses it.
        with pytest.raises(NotOwner, match=f"its owner is now wb epoch {epoch_b}"):
            store_a.write_as("r1", b"a stale checkpoint", epoch_a, old_lease)
        assert store_a.current("r1") == pointer
        assert store_b.load_checkpoint("r1").last_index == 20
        blobs = sorted(p.name for p in (tmp_path / "store" / "r1").glob("*.ckpt"))
        assert all(f"session.{epoch_a}." in n or f"session.{epoch_b}." in n for n in blobs)
        assert f"session.{epoch_a}.000002.ckpt" not in blobs  # the refused one is gone

        logged = [r.message for r in caplog.records]
        assert f"grant robot r1 to worker wa epoch {epoch_a} (lease {old_lease:x})" in logged
        assert f"fence robot r1 on worker wa epoch {epoch_a}" in logged
        assert any(m.startswith(f"grant robot r1 to worker wb epoch {epoch_b}") for m in logged)
        # Back in touch, A gets a new lease and may be granted robots again.
        wait_for(a.live, LEASE_S * 3, "A's new lease")
        assert a.grant("r1") is None  # B's, still
    finally:
        link.close()
        a.close()
        b.close()


def test_a_finished_robot_stays_finished(etcd, keys, tmp_path):
    a, b = _worker(etcd.endpoint, "wa", keys), _worker(etcd.endpoint, "wb", keys)
    store_a, store_b = FencedStore(tmp_path, a), FencedStore(tmp_path, b)
    try:
        epoch_a = a.grant("r1")
        store_a.save_checkpoint("r1", _state(5))
        store_a.save_checkpoint("r1", _state(9, ended=True))
        assert a.release("r1", epoch_a)
        epoch_b = b.grant("r1")
        assert epoch_b > epoch_a
        with pytest.raises(NotOwner, match="the robot has ended"):
            store_b.save_checkpoint("r1", _state(12))
        assert store_b.current("r1").ended and store_b.current("r1").epoch == epoch_a
        restored = store_b.load_checkpoint("r1")
        assert restored.ended and restored.last_index == 9
        # Finished again (the new owner's final checkpoint) is allowed.
        store_b.save_checkpoint("r1", _state(9, ended=True))
        assert store_b.current("r1").epoch == epoch_b
        assert store_b.robots_with_checkpoints() == ["r1"]
        # Only the newest two blobs of a writer are kept.
        for i in range(4):
            store_b.save_checkpoint("r1", _state(9, ended=True))
        assert len(list(tmp_path.glob(f"r1/session.{epoch_b}.*.ckpt"))) == 2
    finally:
        a.close()
        b.close()


@contextmanager
def _two_checkpoints(etcd, keys, tmp_path):
    """Worker "wa" owning r1 with two checkpoints (last_index 5, then 9): yields its store
    and the first checkpoint's pointer."""
    a = _worker(etcd.endpoint, "wa", keys)
    store = FencedStore(tmp_path, a)
    try:
        a.grant("r1")
        store.save_checkpoint("r1", _state(5))
        older = store.current("r1")
        store.save_checkpoint("r1", _state(9))
        yield store, older
    finally:
        a.close()


def test_a_rolled_back_or_dangling_pointer_is_not_trusted(etcd, keys, tmp_path, caplog):
    """Someone with etcd access moves r1's pointer back one checkpoint, then at a file that
    is not there: the worker restores the newest checkpoint on disk (every keyframe it
    acknowledged), says why, and never starts a fresh session over it."""
    import json

    with _two_checkpoints(etcd, keys, tmp_path) as (store, older):
        raw = EtcdClient(etcd.endpoint)
        pointer = json.loads(raw.get(keys.current("r1")).value)
        raw.put(keys.current("r1"), json.dumps({**pointer, "seq": older.seq,
                                                "file": older.file}))
        assert store.load_checkpoint("r1").last_index == 9
        assert "behind the newest on disk" in caplog.text
        raw.put(keys.current("r1"), json.dumps({**pointer, "file": "session.999999.000009.ckpt"}))
        assert store.load_checkpoint("r1").last_index == 9
        assert "names session.999999.000009.ckpt, which is not there: not trusted" in caplog.text


def test_a_pointer_read_just_before_its_writer_moved_it_is_read_again(etcd, keys, tmp_path,
                                                                       caplog):
    """A reader between the owner's blob and its pointer's move sees the pointer one blob
    behind: it reads the pointer again and takes the checkpoint it names then, with no
    claim of a rolled-back pointer (the merger said so as an ERROR when it raced a write)."""
    with _two_checkpoints(etcd, keys, tmp_path) as (store, older):
        reads = []

        def current(robot_id):
            reads.append(robot_id)
            return older if len(reads) == 1 else FencedStore.current(store, robot_id)

        store.current = current
        with caplog.at_level(logging.WARNING, "fleetslam.cloud"):
            assert store.load_checkpoint("r1").last_index == 9
        assert len(reads) == 2
        assert "behind the newest on disk" not in caplog.text


def test_an_owner_key_without_a_lease_is_no_owner(etcd, keys, tmp_path, caplog):
    """An owner key written without a lease (by hand, or with a worker's credentials) is
    refused and removed, and the robot granted: it was never served. An owner's key
    overwritten under it: its next checkpoint is refused, and it stops serving the robot
    (it was served on, every checkpoint refused, the robot stuck) so a new grant follows."""
    raw = EtcdClient(etcd.endpoint)
    raw.put(keys.owner("r1"), "squatter")
    fenced: list = []
    a = _worker(etcd.endpoint, "wa", keys, fenced)
    store = FencedStore(tmp_path, a)
    try:
        epoch = a.grant("r1")
        assert epoch is not None and a.owner("r1").worker == "wa"
        assert "owner key names 'squatter' without a lease" in caplog.text
        store.save_checkpoint("r1", _state(4))
        raw.put(keys.owner("r1"), "squatter")  # overwritten: now lease-less, not a's
        with pytest.raises(NotOwner):
            store.save_checkpoint("r1", _state(8))
        assert fenced and fenced[-1][1] == [("r1", epoch)] and a.epoch("r1") is None
        assert a.grant("r1") > epoch  # granted again, the squatter's key removed
        assert store.load_checkpoint("r1").last_index == 4
    finally:
        a.close()


def test_ended_only_when_the_final_checkpoint_is_durable(etcd, keys, tmp_path,
                                                       tmp_path_factory):
    """The owner key changes under the session before the robot's end: the final checkpoint
    is refused, so the cloud does not say "ended" (it did, after 30 s, while etcd said the
    robot was unfinished): the robot hears why, at once, and keeps what it holds."""
    import json

    from conftest import exact_config, small_scene

    from fleetslam.backend.robot_slam import RobotSlam
    from fleetslam.cloud.session.robot_session import RobotSession
    from fleetslam.datasets.tum import RgbdSequence
    from fleetslam.pipeline.split import run_stages
    from fleetslam.pipeline.states import CapturedFrame
    from fleetslam.transport import keys as wire_keys
    from fleetslam.wire.frames import encode_frame_message

    folder = small_scene(tmp_path_factory, 6)[0]
    seq = RgbdSequence(folder)
    robot = RobotSlam.new(exact_config(), seq.camera)
    messages = []
    for n, f in enumerate(seq):
        state = run_stages(robot.split(3)[0], CapturedFrame(f.index, f.timestamp, f.rgb,
                                                             f.depth_m), robot.sides)
        messages.append(encode_frame_message(state, 3, "r1", n, seq.camera, exact_config().wire))
    a = _worker(etcd.endpoint, "wa", keys)
    store = FencedStore(tmp_path, a)
    replies: list[dict] = []
    session = None
    try:
        a.grant("r1")
        session = RobotSession.open("r1", Hello(3, seq.camera, "test"), exact_config(), store,
                                    lambda k, d: replies.append(json.loads(d))
                                    if k == wire_keys.reply("r1") else None)
        for data in messages:
            session.submit_frame(data, time.monotonic())
        session.drain()
        EtcdClient(etcd.endpoint).put(keys.owner("r1"), "someone else")
        unavailable = [r.index for r in session.state.rows if r.is_keyframe]
        session.submit_control({"type": "end", "last_seq": len(messages) - 1,
                                "unavailable": unavailable}, time.monotonic())
        wait_for(lambda: any(r["type"] in ("ended", "error") for r in replies), 20,
                 "an answer to the end")
    finally:
        if session is not None:
            session.close()
        a.close()
    answer = next(r for r in replies if r["type"] in ("ended", "error"))
    assert answer["type"] == "error" and answer["code"] == "failed", answer
    assert "final checkpoint is not durable" in answer["reason"]
    assert not any(r["type"] == "ended" for r in replies)


def test_an_etcd_wiped_and_started_again_loses_no_checkpoint(tmp_path, keys, caplog):
    """etcd's data lost, a new etcd started: its epochs count from 1 again. The store's
    checkpoints are neither overwritten (a new era's names) nor forgotten (a worker restores
    the newest, and says why); it had started the robot afresh over them."""
    first = EtcdService(tmp_path / "etcd-a").start()
    try:
        a = _worker(first.endpoint, "wa", keys)
        store_a = FencedStore(tmp_path / "store", a)
        epoch_a = a.grant("r1")
        store_a.save_checkpoint("r1", _state(5))
        store_a.save_checkpoint("r1", _state(7))
        a.close()
    finally:
        first.stop()
    before = {p.name: p.read_bytes() for p in (tmp_path / "store" / "r1").glob("session.*")}
    second = EtcdService(tmp_path / "etcd-b").start()  # empty: a new history
    try:
        b = _worker(second.endpoint, "wb", keys)
        store_b = FencedStore(tmp_path / "store", b)
        assert store_b.robots_with_checkpoints() == ["r1"]
        epoch_b = b.grant("r1")
        assert epoch_b <= epoch_a  # etcd counts again: the epoch alone would repeat
        assert store_b.load_checkpoint("r1").last_index == 7
        assert "etcd names no checkpoint, yet its folder holds some" in caplog.text
        store_b.save_checkpoint("r1", _state(9))
        assert "etcd's history was reset" in caplog.text
        after = {p.name: p.read_bytes() for p in (tmp_path / "store" / "r1").glob("session.*")}
        assert all(after.get(name) == data for name, data in before.items())  # none over
        assert store_b.current("r1").file.startswith("session.1-")
        assert store_b.load_checkpoint("r1").last_index == 9
        b.close()
    finally:
        second.stop()


def test_a_paused_coordination_service_fences_every_owner(tmp_path, keys):
    """etcd itself stalls (SIGSTOP) longer than the lease: no renewal reaches it, so every
    worker stops serving within the lease; resumed, the robot is granted again with a larger
    epoch and the old epoch's writes are refused."""
    import os
    import signal

    with EtcdService(tmp_path / "etcd") as etcd:
        fenced: list = []
        a = _worker(etcd.endpoint, "wa", keys, fenced)
        store_a = FencedStore(tmp_path / "store", a)
        try:
            epoch_a, lease_a = a.grant("r1"), a.lease
            store_a.save_checkpoint("r1", _state(3))
            paused = time.monotonic()
            os.kill(etcd.pid, signal.SIGSTOP)
            try:
                wait_for(lambda: fenced, HANG_S, "A to fence itself", interval=0.02)
                # A's deadline (its every check says no from then on, however late its
                # threads run) came from a renewal sent before the pause: 3/4 of the lease
                # after it at most, before etcd can expire the lease (0 once the keeper has
                # given the lease up).
                _, deadline = a._keeper.read()
                assert deadline <= paused + LEASE_S * 0.75
                assert a.epoch("r1") is None
                time.sleep(0.5)  # past the lease at etcd too
            finally:
                os.kill(etcd.pid, signal.SIGCONT)
            b = _worker(etcd.endpoint, "wb", keys)
            try:
                epoch_b = wait_for(lambda: b.grant("r1"), LEASE_S * 3, "B's grant of r1",
                                   interval=0.05)
                assert epoch_b > epoch_a
                with pytest.raises(NotOwner):
                    store_a.write_as("r1", b"stale", epoch_a, lease_a)
                assert store_a.current("r1").epoch == epoch_a  # A's last good one, unmoved
            finally:
                b.close()
        finally:
            a.close()


def test_a_watch_hears_puts_deletes_and_expiries(etcd, keys):
    from fleetslam.cloud.coordination.etcd_gateway import Watch

    client = EtcdClient(etcd.endpoint)
    heard: list = []
    watch = Watch(etcd.endpoint, keys.prefix, heard.extend).start()
    try:
        assert watch.created.wait(5.0), "the watch stream never opened"
        client.put(keys.owner("r1"), "wa")
        client.delete(keys.owner("r1"))
        lease, _ = client.lease_grant(LEASE_S)
        client.put(keys.owner("r2"), "wb", lease)
        started = time.monotonic()
        wait_for(lambda: len(heard) >= 4, LEASE_S * 3, "the lease's expiry to be heard",
                 interval=0.02)
        assert [(e.deleted, e.kv.key.decode()) for e in heard] == [
            (False, keys.owner("r1")), (True, keys.owner("r1")),
            (False, keys.owner("r2")), (True, keys.owner("r2"))]
        assert time.monotonic() - started > LEASE_S - 0.2  # expired, not deleted
    finally:
        watch.close()
    assert not watch._thread.is_alive()


def test_a_watch_hears_that_etcds_history_was_reset(tmp_path):
    """etcd wiped and started again on its address: a running worker's watch had asked for
    revisions after those it heard, which the new etcd would reach only much later (the
    worker never served again). It says so, has its owner re-read, and hears new events."""
    from fleetslam.cloud.coordination.etcd_gateway import Watch

    first = EtcdService(tmp_path / "a").start()
    port = first.client_port
    events: list = []
    resets: list = []
    client = EtcdClient(first.endpoint)
    for i in range(30):
        client.put(f"p/{i}", "x")
    watch = Watch(first.endpoint, "p/", events.extend, retry_s=0.1,
                  on_reset=lambda: resets.append(time.monotonic())).start()
    second = None
    try:
        assert watch.created.wait(10)
        client.put("p/seen", "y")
        wait_for(lambda: any(e.kv.key == b"p/seen" for e in events), 10, "the first event")
        first.stop()
        second = EtcdService(tmp_path / "b", client_port=port).start()  # empty: a new history
        wait_for(lambda: resets, 20, "the watch to hear the reset")
        EtcdClient(second.endpoint).put("p/new", "z")
        wait_for(lambda: any(e.kv.key == b"p/new" for e in events), 20, "an event after it")
    finally:
        watch.close()
        first.stop()
        if second is not None:
            second.stop()


def test_a_robot_hears_that_the_workers_cannot_reach_etcd(tmp_path):
    """etcd out of reach: a worker can be granted no robot, and says so to a robot's hello
    (the robot waited for 30 hellos, then blamed "no cloud" and the access control)."""
    import json
    import os
    import signal

    from test_cloud import FakeRobot

    from fleetslam.cloud.server import CloudServer
    from fleetslam.launch import free_endpoint
    from fleetslam.transport import keys as wire_keys
    from fleetslam.transport.protocol import PROTOCOL
    from fleetslam.transport.zenoh_session import open_connecting

    with EtcdService(tmp_path / "etcd") as etcd:
        config = Config().with_values({"placement.coordination": etcd.endpoint})
        endpoint = free_endpoint()
        server = CloudServer(config, tmp_path / "cloud", endpoint).start()
        client = open_connecting(endpoint)
        robot = FakeRobot(client, "r1", CAMERA)
        os.kill(etcd.pid, signal.SIGSTOP)
        try:
            wait_for(lambda: not server.ownership.live(), LEASE_S * 2, "the worker fenced")
            hello = {"type": "hello", "protocol": PROTOCOL, "offload_at": 3,
                     "camera": CAMERA.to_dict(), "source": "test"}
            client.put(wire_keys.control("r1"), json.dumps(hello).encode())
            answer = robot.reply("error", timeout=10.0)
        finally:
            os.kill(etcd.pid, signal.SIGCONT)
            robot.close()
            client.close()
            server.close()
    assert answer["answer_to"] == "hello" and answer["wait"] is True
    assert f"cannot reach their coordination service (etcd at {etcd.endpoint})" in \
        answer["reason"]

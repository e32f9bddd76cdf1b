"""The emulated robot-to-cloud link: bandwidth, latency, loss, order, robustness."""

from __future__ import annotations

import logging
import threading
import time

import pytest

from conftest import HANG_S

from fleetslam.config import LinkConfig
from fleetslam.transport.link import EmulatedLink


class Received:
    """A thread-safe deliver callback that records what arrived and when (on ``clock``)."""

    def __init__(self, clock=time.monotonic) -> None:
        self.items: list[tuple[str, bytes]] = []
        self.times: list[float] = []
        self._clock = clock
        self._lock = threading.Lock()

    def __call__(self, key: str, data: bytes) -> None:
        with self._lock:
            self.items.append((key, data))
            self.times.append(self._clock())

    @property
    def keys(self) -> list[str]:
        return [key for key, _ in self.items]


class FakeTime:
    """Virtual time: sleep(dt) advances the clock to dt after the sleeping thread last looked."""

    def __init__(self) -> None:
        self.t = 0.0
        self.sleeps: list[float] = []
        self.woke: dict[int, float] = {}  # thread ident -> the virtual time it last woke at
        self._lock = threading.Lock()
        self._seen = threading.local()

    def clock(self) -> float:
        with self._lock:
            self._seen.t = self.t
            return self.t

    def sleep(self, dt: float) -> None:
        with self._lock:
            self.sleeps.append(dt)
            self.t = max(self.t, getattr(self._seen, "t", self.t) + dt)
            self.woke[threading.get_ident()] = self.t

    def link(self, config: LinkConfig, received: Received) -> EmulatedLink:
        return EmulatedLink(config, received, clock=self.clock, sleep=self.sleep)


def test_bandwidth_paces_sends() -> None:
    fake = FakeTime()
    received = Received(fake.clock)
    # 100 kB at 8 Mbps is 0.1 s on the wire: each send returns when its message is sent.
    with fake.link(LinkConfig(bandwidth_mbps=8.0), received) as link:
        for i in range(10):
            assert link.send(f"m{i}", bytes(100_000))
            assert fake.woke[threading.get_ident()] == pytest.approx(0.1 * (i + 1))
    assert received.keys == [f"m{i}" for i in range(10)]
    stats = link.stats
    assert (stats.messages, stats.bytes, stats.delivered) == (10, 1_000_000, 10)
    assert stats.busy_s == pytest.approx(1.0)


def test_threads_share_the_link() -> None:
    fake = FakeTime()
    received = Received(fake.clock)
    link = fake.link(LinkConfig(bandwidth_mbps=8.0), received)

    def sender(name: str) -> None:
        for i in range(5):
            link.send(f"{name}{i}", bytes(100_000))

    threads = [threading.Thread(target=sender, args=(name,)) for name in "ab"]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    link.close()
    # Two senders of 0.5 s each on one link: the sum, not the max; one message at a time.
    assert fake.t == pytest.approx(1.0)
    assert sorted(received.keys) == sorted(f"{n}{i}" for n in "ab" for i in range(5))
    # Each sender's own messages stay in order.
    for name in "ab":
        assert [k for k in received.keys if k[0] == name] == [f"{name}{i}" for i in range(5)]


def test_fake_clock_schedule_and_no_busy_wait() -> None:
    fake = FakeTime()
    received = Received()
    # 1 MB at 1 Mbps: 8 s of virtual wire time, slept in one go.
    link = EmulatedLink(LinkConfig(bandwidth_mbps=1.0), received, clock=fake.clock,
                        sleep=fake.sleep)
    link.send("big", bytes(1_000_000))
    assert fake.t == pytest.approx(8.0)
    link.send("small", bytes(125_000))
    assert fake.t == pytest.approx(9.0)
    link.close()
    assert received.keys == ["big", "small"]
    assert len(fake.sleeps) <= 4
    assert link.stats.busy_s == pytest.approx(9.0)


def test_idle_link_starts_at_now() -> None:
    fake = FakeTime()
    link = EmulatedLink(LinkConfig(bandwidth_mbps=1.0), Received(), clock=fake.clock,
                        sleep=fake.sleep)
    link.send("a", bytes(125_000))
    fake.t += 5.0  # the link idles: the next message does not inherit the gap
    fake.clock()
    link.send("b", bytes(125_000))
    assert fake.t == pytest.approx(7.0)
    link.close()


def test_latency_delays_delivery_not_send() -> None:
    fake = FakeTime()
    received = Received(fake.clock)
    link = fake.link(LinkConfig(latency_ms=200.0), received)
    for i in range(3):
        assert link.send(f"m{i}", b"x" * 100)
    assert threading.get_ident() not in fake.woke  # sending never slept
    link.flush(timeout=HANG_S)
    assert received.keys == ["m0", "m1", "m2"]
    assert received.times == pytest.approx([0.2] * 3)  # delivered a latency after sending
    link.close()


def test_latency_adds_to_wire_time() -> None:
    fake = FakeTime()
    received = Received(fake.clock)
    link = fake.link(LinkConfig(bandwidth_mbps=8.0, latency_ms=100.0), received)
    link.send("m", bytes(100_000))  # 0.1 s on the wire
    assert fake.woke[threading.get_ident()] == pytest.approx(0.1)
    link.flush(timeout=HANG_S)
    assert received.times == pytest.approx([0.2])
    link.close()


def test_order_preserved() -> None:
    received = Received()
    with EmulatedLink(LinkConfig(bandwidth_mbps=100.0, latency_ms=5.0), received) as link:
        for i in range(200):
            link.send("k", i.to_bytes(4, "little") * (1 + i % 7))
    values = [int.from_bytes(data[:4], "little") for _, data in received.items]
    assert values == list(range(200))


def loss_pattern(seed: int, n: int = 2000) -> tuple[list[bool], Received, EmulatedLink]:
    received = Received()
    link = EmulatedLink(LinkConfig(loss=0.2, seed=seed), received)
    sent = [link.send(f"m{i}", b"x" * 10) for i in range(n)]
    link.close()
    return sent, received, link


def test_loss_rate_and_determinism() -> None:
    sent, received, link = loss_pattern(seed=3)
    lost = sent.count(False)
    assert lost / len(sent) == pytest.approx(0.2, abs=0.03)
    # Lost messages never arrive; the others all do, in order.
    assert received.keys == [f"m{i}" for i, ok in enumerate(sent) if ok]
    stats = link.stats
    assert (stats.lost_messages, stats.lost_bytes) == (lost, 10 * lost)
    assert stats.delivered == len(sent) - lost
    assert loss_pattern(seed=3)[0] == sent
    assert loss_pattern(seed=4)[0] != sent


def test_lost_message_still_occupies_link() -> None:
    fake = FakeTime()
    received = Received()
    link = EmulatedLink(LinkConfig(bandwidth_mbps=1.0, loss=0.5, seed=0), received,
                        clock=fake.clock, sleep=fake.sleep)
    sent = [link.send(f"m{i}", bytes(125_000)) for i in range(20)]
    link.close()
    assert False in sent
    assert fake.t == pytest.approx(20.0)  # every message took its second, lost or not
    assert received.keys == [f"m{i}" for i, ok in enumerate(sent) if ok]


def test_unlimited_link_delivers_immediately() -> None:
    received = Received()
    link = EmulatedLink(LinkConfig(), received)
    for i in range(100):
        assert link.send(f"m{i}", bytes(1_000_000))
        assert len(received.items) == i + 1  # delivered before send returned
    link.close()
    assert link.stats.busy_s == 0.0


@pytest.mark.parametrize("kwargs, words", [
    ({"bandwidth_mbps": -1.0}, "bandwidth_mbps"),
    ({"bandwidth_mbps": float("nan")}, "bandwidth_mbps"),
    ({"latency_ms": -5.0}, "latency_ms"),
    ({"loss": 1.0}, "loss"),
    ({"loss": -0.1}, "loss"),
])
def test_bad_config(kwargs: dict[str, float], words: str) -> None:
    with pytest.raises(ValueError, match=words):
        EmulatedLink(LinkConfig(**kwargs), Received())


@pytest.mark.parametrize("config", [LinkConfig(), LinkConfig(latency_ms=10.0)])
def test_deliver_exception_does_not_stop_link(config: LinkConfig,
                                              caplog: pytest.LogCaptureFixture) -> None:
    received = Received()

    def deliver(key: str, data: bytes) -> None:
        if key == "bad":
            raise RuntimeError("receiver broke")
        received(key, data)

    with caplog.at_level(logging.ERROR, logger="fleetslam.link"):
        with EmulatedLink(config, deliver) as link:
            for key in ["a", "bad", "b", "c"]:
                assert link.send(key, b"payload")
    assert received.keys == ["a", "b", "c"]
    errors = [r for r in caplog.records if r.exc_info and "receiver broke" in str(r.exc_info[1])]
    assert len(errors) == 1


def test_close_flushes_and_stops() -> None:
    received = Received()
    threads_before = threading.active_count()
    link = EmulatedLink(LinkConfig(latency_ms=100.0), received)
    assert threading.active_count() == threads_before + 1
    for i in range(5):
        link.send(f"m{i}", b"x")
    link.close()
    assert received.keys == [f"m{i}" for i in range(5)]
    assert threading.active_count() == threads_before
    with pytest.raises(RuntimeError):
        link.send("late", b"x")
    link.close()  # a second close is harmless


def test_flush_timeout() -> None:
    link = EmulatedLink(LinkConfig(latency_ms=300.0), Received())
    link.send("m", b"x")
    with pytest.raises(TimeoutError):
        link.flush(timeout=0.02)
    link.close()

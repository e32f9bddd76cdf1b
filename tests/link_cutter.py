"""A TCP relay on loopback that a test can cut and heal: one worker talks to etcd through it,
so only that worker is partitioned from the coordination service (etcd itself keeps running
for the others). Cut, it forwards nothing and connects nothing new, keeping what is open
open (a partition, not a refusal: the client sees its requests time out); healed, what
waited is delivered, as TCP would after a partition. Slowed, every byte arrives ``delay_s``
after it was sent (a congested link's queue, without its drops)."""

from __future__ import annotations

import select
import socket
import threading
import time
from collections import deque


class LinkCutter:
    def __init__(self, target_port: int) -> None:
        self.target = ("127.0.0.1", target_port)
        self._listener = socket.create_server(("127.0.0.1", 0))
        self.port = int(self._listener.getsockname()[1])
        self._up = threading.Event()
        self._up.set()
        self._closed = threading.Event()
        self.delay_s = 0.0
        threading.Thread(target=self._accept, daemon=True).start()

    @property
    def endpoint(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def cut(self) -> None:
        self._up.clear()

    def heal(self) -> None:
        self._up.set()

    def close(self) -> None:
        self._closed.set()
        self._up.set()
        self._listener.close()

    def _accept(self) -> None:
        while not self._closed.is_set():
            try:
                client, _ = self._listener.accept()
            except OSError:
                return
            threading.Thread(target=self._relay, args=(client,), daemon=True).start()

    def _relay(self, a: socket.socket) -> None:
        while not self._up.wait(0.05):  # a connection made while cut waits for the heal
            if self._closed.is_set():
                a.close()
                return
        try:
            b = socket.create_connection(self.target, timeout=2.0)
        except OSError:
            a.close()
            return
        peers = {a: b, b: a}
        # Bytes on their way: (when they arrive, where to, what), in order.
        line: deque[tuple[float, socket.socket, bytes]] = deque()
        try:
            while not self._closed.is_set():
                if not self._up.is_set():
                    self._up.wait(0.05)  # held, not forwarded: bytes wait in the buffers
                    continue
                while line and line[0][0] <= time.monotonic():
                    _, to, data = line.popleft()
                    to.sendall(data)
                wait = 0.05 if not line else min(0.05, max(0.0, line[0][0] - time.monotonic()))
                ready, _, _ = select.select(list(peers), [], [], wait)
                for s in ready:
                    data = s.recv(65536)
                    if not data:
                        return
                    line.append((time.monotonic() + self.delay_s, peers[s], data))
        except OSError:
            return
        finally:
            a.close()
            b.close()

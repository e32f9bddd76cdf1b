"""A local etcd for one run of many cloud workers (``fleetslam demo --workers N``).

etcd is the coordination service the workers agree on robot ownership through (leases,
transactions: ``ownership.py``); Zenoh keeps carrying the data. The single-process cloud
never starts one. Debian's ``etcd-server`` package provides the binary
(``scripts/setup-system.sh`` installs it).

The service lives only as long as the run: its data under the run's folder, its client and
peer ports free ports on loopback (nothing outside the machine reaches it), stopped on exit.
"""

from __future__ import annotations

import atexit
import json
import logging
import shutil
import signal
import socket
import subprocess
import time
import urllib.error
import urllib.request
from pathlib import Path
from types import TracebackType

from fleetslam.cloud.coordination.etcd_gateway import EtcdTls

log = logging.getLogger("fleetslam.coordination")

BINARY = "etcd"
INSTALL_HINT = ("install it with scripts/setup-system.sh (Debian/Ubuntu: "
                "`apt-get install etcd-server`)")


class CoordinationServiceError(RuntimeError):
    pass


def etcd_binary(binary: str = BINARY) -> str | None:
    """The etcd executable's path, None if it is not installed."""
    return shutil.which(binary)


def _free_port() -> int:
    # Bound and closed at once: etcd binds it a moment later (a race another program could
    # win on a busy machine; start() then fails with etcd's own message and may be retried).
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class EtcdService:
    """One etcd member on loopback. ``with EtcdService(run_dir / "etcd") as etcd:`` then
    ``etcd.endpoint`` is the URL clients use."""

    def __init__(self, data_dir: Path, start_deadline_s: float = 10.0,
                 binary: str = BINARY, also_listen: tuple[str, ...] = (),
                 certs: Path | None = None, client_port: int = 0) -> None:
        """``also_listen``: IP addresses of this machine where clients reach it too, on the
        same port (a partition experiment's worker in a network namespace), besides
        loopback. ``certs``: the lab's coordination TLS folder (``fleetslam certs``'s
        <lab>/etcd): clients then need https and a certificate of its CA."""
        self.data_dir = Path(data_dir)
        self.certs = None if certs is None else Path(certs)
        self.also_listen = tuple(also_listen)
        self.start_deadline_s = start_deadline_s
        self.binary = binary
        self.client_port = client_port  # 0: a free one at start
        self.peer_port = 0
        self._process: subprocess.Popen[bytes] | None = None

    @property
    def scheme(self) -> str:
        return "http" if self.certs is None else "https"

    @property
    def endpoint(self) -> str:
        return f"{self.scheme}://127.0.0.1:{self.client_port}"

    @property
    def tls(self) -> EtcdTls | None:
        """What a client of this etcd needs (None: plain http)."""
        return None if self.certs is None else EtcdTls.from_folder(self.certs)

    @property
    def log_path(self) -> Path:
        return self.data_dir.with_name(self.data_dir.name + ".log")

    @property
    def pid(self) -> int | None:
        return None if self._process is None else self._process.pid

    def start(self) -> "EtcdService":
        path = etcd_binary(self.binary)
        if path is None:
            raise CoordinationServiceError(
                f"the coordination service needs the `{self.binary}` program, which is not "
                f"on PATH: {INSTALL_HINT}")
        self.data_dir.parent.mkdir(parents=True, exist_ok=True)
        self.client_port, self.peer_port = self.client_port or _free_port(), _free_port()
        peer = f"http://127.0.0.1:{self.peer_port}"
        clients = ",".join([self.endpoint] + [f"{self.scheme}://{host}:{self.client_port}"
                                              for host in self.also_listen])
        args = [path, "--name", "fleetslam", "--data-dir", str(self.data_dir),
                "--listen-client-urls", clients, "--advertise-client-urls", clients,
                "--listen-peer-urls", peer, "--initial-advertise-peer-urls", peer,
                "--initial-cluster", f"fleetslam={peer}",
                "--initial-cluster-state", "new", "--logger", "zap", "--log-outputs", "stderr",
                # Every checkpoint moves a pointer: keep the last 10k revisions, not all of
                # a long run's (a watch resuming from before them starts at the oldest kept).
                "--auto-compaction-mode", "revision", "--auto-compaction-retention", "10000"]
        if self.certs is not None:  # etcd's documented transport security: mutual TLS
            args += ["--cert-file", str(self.certs / "server.pem"),
                     "--key-file", str(self.certs / "server.key"),
                     "--client-cert-auth", "--trusted-ca-file", str(self.certs / "ca.pem")]
        with open(self.log_path, "ab") as out:
            self._process = subprocess.Popen(args, stdout=out, stderr=out,
                                             stdin=subprocess.DEVNULL)
        # Stopped when this interpreter exits, whatever the caller forgot (not on SIGKILL).
        atexit.register(self.stop)
        try:
            self._wait_healthy()
        except BaseException:
            self.stop()
            raise
        log.info("coordination service etcd (pid %d) at %s, data %s", self._process.pid,
                 self.endpoint, self.data_dir)
        return self

    def _log_tail(self, lines: int = 5) -> str:
        try:
            text = self.log_path.read_text(errors="replace").strip().splitlines()
        except OSError:
            return "(no log)"
        return "\n  ".join(text[-lines:]) or "(empty log)"

    def _wait_healthy(self) -> None:
        assert self._process is not None
        deadline = time.monotonic() + self.start_deadline_s
        last = "no answer yet"
        while True:
            code = self._process.poll()
            if code is not None:
                raise CoordinationServiceError(
                    f"etcd exited with status {code} while starting (data {self.data_dir}); "
                    f"the end of {self.log_path}:\n  {self._log_tail()}")
            # Never past the deadline: etcd may have bound its port and not serve yet.
            timeout = min(1.0, max(0.001, deadline - time.monotonic()))
            tls = self.tls
            try:
                with urllib.request.urlopen(f"{self.endpoint}/health", timeout=timeout,
                                            context=None if tls is None else tls.context()
                                            ) as reply:
                    if json.loads(reply.read()).get("health") == "true":
                        return
                    last = "it answered, not healthy yet"
            except (OSError, urllib.error.URLError, ValueError) as exc:
                last = str(exc)
            if time.monotonic() > deadline:
                raise CoordinationServiceError(
                    f"etcd at {self.endpoint} was not healthy within {self.start_deadline_s:g}"
                    f" s ({last}); the end of {self.log_path}:\n  {self._log_tail()}")
            time.sleep(0.05)

    def stop(self, deadline_s: float = 5.0) -> None:
        """SIGTERM, then SIGKILL after ``deadline_s``."""
        process, self._process = self._process, None
        if process is None:
            return
        atexit.unregister(self.stop)
        if process.poll() is not None:
            return
        process.send_signal(signal.SIGTERM)
        process.send_signal(signal.SIGCONT)  # a paused etcd (a test's SIGSTOP) must hear it
        try:
            process.wait(deadline_s)
        except subprocess.TimeoutExpired:
            log.warning("etcd (pid %d) did not stop within %g s of SIGTERM: killing it",
                        process.pid, deadline_s)
            process.kill()
            process.wait(deadline_s)

    def __enter__(self) -> "EtcdService":
        return self.start()

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.stop()

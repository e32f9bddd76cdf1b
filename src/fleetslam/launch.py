"""Starting the cloud and robots as separate processes, and talking to a running cloud:
what ``fleetslam demo``, the tests and the benchmarks share."""

from __future__ import annotations

import logging
import math
import os
import queue
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from fleetslam.transport import keys, protocol
from fleetslam.transport.reachability import no_answer
from fleetslam.transport.zenoh_session import open_connecting, put

log = logging.getLogger("fleetslam.client")


def free_endpoint() -> str:
    """A loopback TCP endpoint nobody listens on right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def _python(config_path: str | None, zenoh_config: str | None = None) -> list[str]:
    cmd = [sys.executable, "-m", "fleetslam.cli"]
    cmd += ["--config", str(config_path)] if config_path else []
    return cmd + (["--zenoh-config", str(zenoh_config)] if zenoh_config else [])


def start_cloud(endpoint: str, out_dir: Path, log_path: Path, config_path: str | None = None,
                extra: list[str] | None = None, zenoh_config: str | None = None
                ) -> subprocess.Popen:
    log_path.parent.mkdir(parents=True, exist_ok=True)
    cmd = _python(config_path, zenoh_config) + ["cloud", "--listen", endpoint, "--out",
                                                str(out_dir), *(extra or [])]
    return subprocess.Popen(cmd, stdout=open(log_path, "ab"), stderr=subprocess.STDOUT,
                            env=_env())


def start_router(endpoint: str, log_path: Path, zenoh_config: str | None = None
                 ) -> subprocess.Popen:
    log_path.parent.mkdir(parents=True, exist_ok=True)
    cmd = _python(None, zenoh_config) + ["router", "--listen", endpoint]
    return subprocess.Popen(cmd, stdout=open(log_path, "ab"), stderr=subprocess.STDOUT,
                            env=_env())


def start_worker(router: str, worker_id: str, out_dir: Path, log_path: Path,
                 config_path: str | None = None, extra: list[str] | None = None,
                 zenoh_config: str | None = None, cpus: list[int] | None = None,
                 prefix: list[str] | None = None) -> subprocess.Popen:
    """A cloud worker connected to the router at ``router``, sharing the store ``out_dir``;
    ``cpus``: pinned to these cores (Linux); ``prefix``: a command that runs it (``ip netns
    exec NS``: a worker on a machine of its own for a partition experiment)."""
    log_path.parent.mkdir(parents=True, exist_ok=True)
    cmd = (prefix or []) + _python(config_path, zenoh_config) + [
        "cloud", "--connect", router, "--worker-id", worker_id, "--out", str(out_dir),
        *(extra or [])]
    pin = (lambda: os.sched_setaffinity(0, cpus)) if cpus else None
    return subprocess.Popen(cmd, stdout=open(log_path, "ab"), stderr=subprocess.STDOUT,
                            env=_env(), preexec_fn=pin)


def start_robot(endpoint: str, robot_id: str, source: str, offload_at: int | str,
                log_path: Path, report_path: Path | None = None,
                config_path: str | None = None, extra: list[str] | None = None,
                zenoh_config: str | None = None,
                pre_exec: Callable[[], None] | None = None) -> subprocess.Popen:
    """``pre_exec``: run in the child before the robot starts (bench/robot_cpu.py: join a
    CPU cgroup, pin to a core)."""
    log_path.parent.mkdir(parents=True, exist_ok=True)
    cmd = _python(config_path, zenoh_config) + [
        "--quiet", "robot", "--connect", endpoint, "--id", robot_id, "--source", source,
        "--offload-at", str(offload_at)]
    if report_path is not None:
        cmd += ["--report", str(report_path)]
    return subprocess.Popen(cmd + (extra or []), stdout=open(log_path, "ab"),
                            stderr=subprocess.STDOUT, env=_env(), preexec_fn=pre_exec)


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env.setdefault("OMP_WAIT_POLICY", "passive")
    return env


def dump_stacks(process: subprocess.Popen, wait_s: float = 1.0) -> None:
    """Ask a running fleetslam process for every thread's stack (SIGUSR1, cli.main: written
    to its stderr, i.e. its log) and give it ``wait_s`` to write them; it goes on running."""
    if process.poll() is None and hasattr(signal, "SIGUSR1"):
        process.send_signal(signal.SIGUSR1)
        time.sleep(wait_s)


def stop(process: subprocess.Popen, timeout: float = 20.0) -> int:
    """SIGTERM (the cloud closes cleanly), then SIGKILL if it does not."""
    if process.poll() is None:
        process.send_signal(signal.SIGTERM)
        try:
            process.wait(timeout)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
    return process.returncode


def stop_all(processes: list[subprocess.Popen], timeout: float = 20.0) -> None:
    """SIGTERM to all at once (cloud workers stopping together do not hand their robots to
    each other one by one), then as :func:`stop`."""
    for p in processes:
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
    for p in processes:
        stop(p, timeout)


class CloudClient:
    """Ask a running cloud something over its control key (status, merge)."""

    def __init__(self, endpoint: str, reach_deadline_s: float = 600.0,
                 zenoh_config: str | None = None, silence_hint_s: float | None = None,
                 deadline_setting: str = "transport.reach_deadline_s",
                 refused_ends: bool = False) -> None:
        """``silence_hint_s``: when the open session has heard no answer this long, say
        what to check (a command's user waits; None: say nothing). ``deadline_setting``
        names ``reach_deadline_s`` in what is said; ``refused_ends``: a refused connection
        (nothing listens there) is an error at once (an operator's command), not waited
        out (a cloud starting)."""
        self.endpoint = endpoint
        self.zenoh_config = zenoh_config
        self.silence_hint_s = silence_hint_s
        self._session = open_connecting(endpoint, reach_deadline_s, zenoh_config,
                                        setting=deadline_setting, refused_ends=refused_ends)
        self._replies: queue.Queue = queue.Queue()
        self._sub = self._session.declare_subscriber(
            keys.CLOUD_REPLY, lambda s: self._replies.put(s.payload.to_bytes()))

    def request(self, message: protocol.Request, reply_type: type, timeout: float,
                resend_s: float = 1.0, answered: bool = False) -> Any:
        """Send ``message`` until the cloud's reply to its id arrives; replies to other
        requests (other clients') are ignored. ``answered``: the cloud answered this client
        before, so its silence is work, not a refusal."""
        rid = message.id
        start = time.monotonic()
        deadline = start + timeout
        sent = -math.inf
        hint_at = math.inf if answered or self.silence_hint_s is None \
            else start + self.silence_hint_s
        while time.monotonic() < deadline:
            if time.monotonic() - sent > resend_s:
                put(self._session, keys.CLOUD_CONTROL, protocol.encode(message))
                sent = time.monotonic()
            if time.monotonic() >= hint_at:
                hint_at = math.inf
                log.warning("no answer from the cloud at %s yet (%.0f s): %s; waiting up to "
                            "%.0f s", self.endpoint, time.monotonic() - start,
                            no_answer(self.endpoint, self.zenoh_config), timeout)
            reply = self._next_reply(0.2)
            if reply is None or reply.id != rid:
                continue
            if isinstance(reply, reply_type):
                return reply
            if isinstance(reply, protocol.Error):
                raise RuntimeError(f"cloud: {reply.reason}")
        if answered:
            raise TimeoutError(f"the cloud at {self.endpoint} answered but sent no "
                               f"'{reply_type.TYPE}' within {timeout:.0f} s")
        raise TimeoutError(f"no answer from the cloud at {self.endpoint} within "
                           f"{timeout:.0f} s: {no_answer(self.endpoint, self.zenoh_config)}")

    def _next_reply(self, timeout: float) -> protocol.OperatorReply | None:
        """The next reply heard within ``timeout`` (one that does not parse is said)."""
        try:
            return protocol.parse_operator_reply(self._replies.get(timeout=timeout))
        except queue.Empty:
            return None
        except ValueError as exc:
            log.warning("a reply from the cloud at %s rejected: %s", self.endpoint, exc)
            return None

    def ping(self, timeout: float) -> dict[str, Any]:
        """The first cloud worker's status answer: the cloud is there and answers us."""
        return self.request(protocol.Request("status"), protocol.StatusReply,
                            timeout).message()

    def status(self, timeout: float = 30.0, gather_s: float = 2.0) -> dict[str, Any]:
        """Every cloud worker's answer in one: all robots (each with the worker serving it),
        the live workers and the placement. Waits for the answers of the workers the first
        answer lists, at most ``gather_s`` more."""
        request = protocol.Request("status")
        first = self.request(request, protocol.StatusReply, timeout).message()
        answers = {first.get("worker"): first}
        expected = set(first.get("workers") or [first.get("worker")])
        deadline = time.monotonic() + gather_s
        while not expected <= set(answers) and time.monotonic() < deadline:
            reply = self._next_reply(0.1)
            if isinstance(reply, protocol.StatusReply) and reply.id == request.id:
                answers[reply.worker] = reply.message()
                expected |= set(reply.workers)
        # The merger's view of the global map: the worker whose id sorts first merges.
        merged = dict(answers[min(answers, key=str)])
        merged["robots"] = {r: v for a in answers.values() for r, v in a["robots"].items()}
        merged["answered"] = sorted(str(w) for w in answers)
        return merged

    def merge(self, timeout: float = 600.0, answered: bool = False) -> dict[str, Any]:
        # Resent with the same id until answered: the cloud merges once per id.
        return self.request(protocol.Request("merge"), protocol.Merged, timeout,
                            resend_s=2.0, answered=answered).summary

    def close(self) -> None:
        self._sub.undeclare()
        self._session.close()

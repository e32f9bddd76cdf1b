"""A network namespace joined to the host by a veth pair, for partition experiments: a process
started inside (``prefix() + cmd``) reaches the host only over the veth, so cutting the
veth's host side (``ip link set ... down``) partitions that process from everything on the
host while the rest of the machine goes on; ``shape`` puts a token-bucket filter (``tc tbf``)
on both ends instead (a congested link). Needs root and ``ip``.

Names carry the creating process's id (``fs-part-<pid>``, veths ``fsp<pid>h`` / ``fsp<pid>n``),
so :func:`remove_leftovers` can remove what a crashed run left without touching a live
run's. Every command has a deadline (``ip`` never waits on the network, but a wedged netlink
must not hang a run)."""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import time

PREFIX = "fs-part-"
_NS = re.compile(rf"^{PREFIX}(\d+)\b")
_VETH = re.compile(r"^fsp(\d+)[hn]$")
COMMAND_DEADLINE_S = 10.0


class NetnsError(RuntimeError):
    pass


def _run(*args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    try:
        done = subprocess.run(list(args), capture_output=True, text=True,
                              timeout=COMMAND_DEADLINE_S)
    except subprocess.TimeoutExpired:
        raise NetnsError(f"`{' '.join(args)}` did not return within "
                         f"{COMMAND_DEADLINE_S:g} s") from None
    if check and done.returncode != 0:
        raise NetnsError(f"`{' '.join(args)}` failed ({done.returncode}): "
                         f"{done.stderr.strip()}")
    return done


def unavailable() -> str | None:
    """Why namespaces cannot be made here (None: they can): not root, no ``ip``, or the
    kernel refuses."""
    if os.geteuid() != 0:
        return "network namespaces need root"
    if shutil.which("ip") is None:
        return "the `ip` program (iproute2) is not installed"
    probe = f"{PREFIX}probe-{os.getpid()}"
    made = _run("ip", "netns", "add", probe, check=False)
    if made.returncode != 0:
        return f"`ip netns add` fails: {made.stderr.strip()}"
    _run("ip", "netns", "del", probe, check=False)
    return None


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_leftovers() -> list[str]:
    """Namespaces and veths of runs whose process is gone (a crash, a SIGKILL): the processes
    still inside such a namespace are killed (by their ids), then the namespace and veth go.
    What was removed."""
    removed = []
    listed = _run("ip", "netns", "list", check=False).stdout.splitlines()
    for line in listed:
        name = line.split()[0] if line.split() else ""
        m = _NS.match(name)
        probe = name.startswith(f"{PREFIX}probe-")
        owner = int(name.rsplit("-", 1)[1]) if probe else (int(m.group(1)) if m else None)
        if owner is None or _alive(owner):
            continue
        for pid in _run("ip", "netns", "pids", name, check=False).stdout.split():
            try:
                os.kill(int(pid), signal.SIGKILL)
            except (ProcessLookupError, ValueError):
                pass
        _run("ip", "netns", "del", name, check=False)
        removed.append(name)
    for line in _run("ip", "-o", "link", "show", check=False).stdout.splitlines():
        parts = line.split(":")
        if len(parts) < 2:
            continue
        name = parts[1].strip().split("@")[0]
        m = _VETH.match(name)
        if m and not _alive(int(m.group(1))):
            _run("ip", "link", "del", name, check=False)
            removed.append(name)
    return removed


class NamespaceLink:
    """``with NamespaceLink() as link:`` a namespace ``link.name`` whose address is
    ``link.inside_ip``; the host's end of the veth is ``link.host_ip`` (a /30 of 10.231/16
    picked from this process's id, so two runs at once do not collide)."""

    def __init__(self) -> None:
        pid = os.getpid()
        self.name = f"{PREFIX}{pid}"
        self.host_dev, self.inside_dev = f"fsp{pid}h", f"fsp{pid}n"
        block = (pid % 16384) * 4
        base = f"10.231.{block // 256}."
        self.host_ip, self.inside_ip = f"{base}{block % 256 + 1}", f"{base}{block % 256 + 2}"
        self._made = False
        self.events: list[tuple[float, str]] = []  # (time.time(), what) of every change

    def prefix(self) -> list[str]:
        """Run a command inside: ``ip netns exec NAME`` (which execs it: its pid is the
        command's, signals reach it directly)."""
        return ["ip", "netns", "exec", self.name]

    def _inside(self, *args: str) -> None:
        _run(*self.prefix(), *args)

    def create(self) -> "NamespaceLink":
        self._made = True
        _run("ip", "netns", "add", self.name)
        _run("ip", "link", "add", self.host_dev, "type", "veth", "peer", "name", self.inside_dev)
        _run("ip", "link", "set", self.inside_dev, "netns", self.name)
        _run("ip", "addr", "add", f"{self.host_ip}/30", "dev", self.host_dev)
        _run("ip", "link", "set", self.host_dev, "up")
        self._inside("ip", "addr", "add", f"{self.inside_ip}/30", "dev", self.inside_dev)
        self._inside("ip", "link", "set", self.inside_dev, "up")
        self._inside("ip", "link", "set", "lo", "up")
        self._await_up()
        return self

    def _await_up(self, deadline_s: float = 5.0) -> None:
        """Until both ends report carrier (a veth's comes a moment after ``up``)."""
        deadline = time.monotonic() + deadline_s
        while True:
            states = [_run("cat", f"/sys/class/net/{self.host_dev}/operstate", check=False),
                      _run(*self.prefix(), "cat", f"/sys/class/net/{self.inside_dev}/operstate",
                           check=False)]
            if all(s.stdout.strip() == "up" for s in states):
                return
            if time.monotonic() > deadline:
                raise NetnsError(f"the veth {self.host_dev}/{self.inside_dev} of namespace "
                                 f"{self.name} not up within {deadline_s:g} s "
                                 f"({', '.join(s.stdout.strip() or '?' for s in states)})")
            time.sleep(0.05)

    def cut(self) -> float:
        """The host's end down: nothing passes either way (the namespace's end keeps its
        address; its packets go nowhere, as on a lost machine). When, as time.time()."""
        _run("ip", "link", "set", self.host_dev, "down")
        return self._event("cut")

    def heal(self) -> float:
        _run("ip", "link", "set", self.host_dev, "up")
        self._await_up()
        return self._event("heal")

    def shape(self, rate: str, burst: str = "32kbit", latency: str = "400ms") -> float:
        """A token bucket of ``rate`` on both ends' egress (tc tbf; no netem on this kernel):
        more than ``rate`` queues up to ``latency``, then is dropped."""
        tbf = ["qdisc", "replace", "dev", "{dev}", "root", "tbf", "rate", rate, "burst", burst,
               "latency", latency]
        _run("tc", *[a.replace("{dev}", self.host_dev) for a in tbf])
        self._inside("tc", *[a.replace("{dev}", self.inside_dev) for a in tbf])
        return self._event(f"shape {rate}")

    def unshape(self) -> float:
        _run("tc", "qdisc", "del", "dev", self.host_dev, "root", check=False)
        _run(*self.prefix(), "tc", "qdisc", "del", "dev", self.inside_dev, "root", check=False)
        return self._event("unshape")

    def _event(self, what: str) -> float:
        now = time.time()
        self.events.append((now, what))
        return now

    def pids(self) -> list[int]:
        return [int(p) for p in _run("ip", "netns", "pids", self.name, check=False).stdout.split()]

    def close(self) -> None:
        """Kill what still runs inside (by id), then remove the namespace (its veth end goes
        with it, and the host's end with the pair)."""
        if not self._made:
            return
        self._made = False
        for pid in self.pids():
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        _run("ip", "netns", "del", self.name, check=False)
        _run("ip", "link", "del", self.host_dev, check=False)

    def __enter__(self) -> "NamespaceLink":
        try:
            return self.create()
        except BaseException:
            self.close()
            raise

    def __exit__(self, *exc: object) -> None:
        self.close()

"""Many workers without split brain: one of two cloud workers partitioned from the rest by a
network namespace, in five cases, under the liveliness placement or etcd ownership.

    sudo .venv/bin/python bench/partition.py [--cases lost,heal-larger,...] \
        [--placement liveliness|etcd] [--runs 1] [--rate 10]

Per case, on this host: (etcd when ``--placement etcd``), a Zenoh router (``fleetslam
router``) and worker A; worker B inside a network namespace ``fs-part-<pid>`` behind a veth
pair (tests/netns_link.py), reaching the router and etcd only through it. Plain TCP, not the
demo's TLS lab (the observer below joins the router as one more client, which the lab's
access control would refuse); Zenoh shared memory off for B (frames would bypass the veth).
Four robots (processes, as ``fleetslam demo`` runs them) play overlapping pieces of 7-Scenes
redkitchen at offloading point 3, ``--rate`` fps each. ``--cut-at`` s after the first
feedback, B's link is cut on the host side (``ip link set <veth> down``):

  lost          the machine is lost for good: B cut to the end (then SIGKILLed);
  heal-larger   the partition heals after ``--heal-after`` s; B has the larger worker id;
  heal-smaller  the same; B has the smaller id (the liveliness rule keeps the smaller id's
                robots, the stale ones);
  lost-stopped  cut for good, and B stopped (SIGTERM) ``--stop-after`` s after the cut,
                while still cut off (it writes its last checkpoints to the shared store);
  congested     no cut: a token bucket of ``--tbf-rate`` on both ends of the veth for
                ``--tbf-s`` s (tc tbf; this kernel has no netem): no failover, no flapping.

Measured: a passive Zenoh client on the host (the observer) records every feedback to the robots
(time, robot, frame index). Failover: cut -> the first feedback to a robot B owned at the cut after
A was granted it (ownership from the workers' logs, bench/ownership_log.py). The robot's longest
pause (robot_report.json: the longest time between two feedbacks) and the fleet's longest silence
after the cut (no feedback to any robot) say what the robots felt: the router goes on forwarding to
B until Zenoh's own lease (10 s) expires B's session. Frames lost: frames the robot sent that no
feedback answered; answered twice: frames with more than one feedback. Acknowledged keyframes lost:
keyframes in the robot's report (robot_report.json) acknowledged by the cloud, missing from the
robot's final checkpoint in the store (fenced_store.stored_run: liveliness,
``<robot>/session.ckpt``; etcd, the file ``fleetslam/current/<robot>`` names), read after every
worker stopped. One owner: no robot's ownership intervals of two workers overlap. Merge groups and
joint ATE as bench/failover.py (ground truth only after). Writes bench/results/partition.json
(``--out``)."""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT / "src"), str(ROOT / "tests"), str(ROOT / "bench")]
# The processes it starts run this tree's fleetslam too (an editable install may point at
# another checkout).
os.environ["PYTHONPATH"] = os.pathsep.join(
    [str(ROOT / "src"), *filter(None, [os.environ.get("PYTHONPATH")])])

import ownership_log  # noqa: E402
from netns_link import NamespaceLink, remove_leftovers, unavailable  # noqa: E402
from shared_data import SEVEN_SCENES  # noqa: E402

from fleetslam.cloud.coordination.coordination_service import EtcdService  # noqa: E402
from fleetslam.cloud.coordination.fenced_store import FencedStore, stored_run  # noqa: E402
from fleetslam.datasets.recording import open_source  # noqa: E402
from fleetslam.evaluation.fleet import score_fleet  # noqa: E402
from fleetslam.launch import (CloudClient, free_endpoint, start_robot,  # noqa: E402
                              start_router, start_worker)
from fleetslam.outputs import ROBOT_REPORT, add_robot_reports  # noqa: E402
from fleetslam.tables import format_table  # noqa: E402
from fleetslam.transport import keys  # noqa: E402
from fleetslam.transport.zenoh_session import open_connecting  # noqa: E402
from fleetslam.wire.messages import decode_feedback  # noqa: E402

PIECES = ["0-199", "130-329", "260-459", "400-599"]  # bench/failover.py's
PLACEMENTS = ("liveliness", "etcd")


@dataclass(frozen=True)
class Case:
    name: str
    heal: bool = False  # the cut heals after heal_after_s
    b_larger_id: bool = True  # B's worker id sorts after A's
    stop_b: bool = False  # B is SIGTERMed stop_after_s after the cut, still cut off
    congest: bool = False  # tbf instead of a cut


CASES = {
    "lost": Case("machine lost, never back"),
    "heal-larger": Case("heals, isolated has larger id", heal=True),
    "heal-smaller": Case("heals, isolated has smaller id", heal=True, b_larger_id=False),
    "lost-stopped": Case("machine lost, isolated stopped", stop_b=True),
    "congested": Case("congested link (tbf)", congest=True),
}


@dataclass(frozen=True)
class Timing:
    cut_at_s: float = 8.0
    heal_after_s: float = 15.0
    stop_after_s: float = 5.0
    tbf_rate: str = "1mbit"
    tbf_s: float = 20.0
    rate: str = "10"
    frames: int | None = None  # per robot (None: the whole piece)
    robots: int = 4
    start_deadline_s: float = 90.0
    run_deadline_s: float = 600.0
    merge_deadline_s: float = 120.0


class FeedbackObserver:
    """A Zenoh client beside the robots hearing every feedback and reply (time.time())."""

    def __init__(self, endpoint: str) -> None:
        self.feedback: list[tuple[float, str, int]] = []  # (time, robot, frame index)
        self.welcomes: list[tuple[float, str, dict[str, Any]]] = []
        self._lock = threading.Lock()
        self._session = open_connecting(endpoint, 30.0)
        self._subs = [
            self._session.declare_subscriber(f"{keys.ROOT}/*/feedback", self._on_feedback),
            self._session.declare_subscriber(f"{keys.ROOT}/*/reply", self._on_reply)]

    def _on_feedback(self, sample: Any) -> None:
        now = time.time()
        try:
            header, fb = decode_feedback(sample.payload.to_bytes())
        except Exception:  # a damaged message is the robot's to reject; not counted here
            return
        with self._lock:
            self.feedback.append((now, header.robot_id, fb.frame_index))

    def _on_reply(self, sample: Any) -> None:
        now = time.time()
        try:
            message = json.loads(sample.payload.to_bytes())
        except ValueError:
            return
        if message.get("type") == "welcome":
            robot = str(sample.key_expr).split("/")[1]
            with self._lock:
                self.welcomes.append((now, robot, message))

    def first_feedback(self) -> float | None:
        with self._lock:
            return self.feedback[0][0] if self.feedback else None

    def answered(self, robot: str) -> dict[int, int]:
        """Frame index -> feedbacks heard for it."""
        counts: dict[int, int] = {}
        with self._lock:
            for _, r, index in self.feedback:
                if r == robot:
                    counts[index] = counts.get(index, 0) + 1
        return counts

    def longest_silence(self, start: float, end: float) -> float:
        """The longest time in [start, end] without feedback to any robot (the whole fleet
        waiting, not one robot)."""
        with self._lock:
            times = sorted(t for t, _, _ in self.feedback if start <= t <= end)
        marks = [start, *times, end] if times else [start, end]
        return max(b - a for a, b in zip(marks, marks[1:]))

    def first_after(self, robot: str, t: float) -> float | None:
        with self._lock:
            return next((ft for ft, r, _ in self.feedback if r == robot and ft > t), None)

    def close(self) -> None:
        for sub in self._subs:
            sub.undeclare()
        self._session.close()


def _zenoh_config_without_shm(path: Path) -> Path:
    """fleetslam's own client defaults (transport/zenoh_session.py) and no shared memory: a
    worker in a namespace shares the host's /dev/shm, so Zenoh would hand it frames through
    memory instead of over the veth the experiment cuts."""
    path.write_text(json.dumps({"mode": "client", "scouting": {"multicast": {"enabled": False}},
                                "transport": {"shared_memory": {"enabled": False}}}, indent=2))
    return path


def _await_workers(client: CloudClient, workers: set[str], deadline_s: float) -> None:
    deadline = time.monotonic() + deadline_s
    answered: list[str] = []
    while time.monotonic() < deadline:
        try:
            answered = client.status(timeout=max(1.0, deadline - time.monotonic()),
                                     gather_s=2.0)["answered"]
        except TimeoutError:
            continue
        if workers <= set(answered):
            return
        time.sleep(0.5)
    raise TimeoutError(f"workers {', '.join(sorted(workers))} did not all answer the status "
                       f"within {deadline_s:.0f} s (answered: {', '.join(answered) or 'none'})")


def _acknowledged_lost(out: Path, robot: str, report: dict[str, Any], etcd: str | None
                       ) -> dict[str, Any]:
    """The robot's acknowledged keyframes that its final checkpoint does not hold, read the
    way its placement's store does (fenced_store.stored_run: with etcd, the checkpoint the
    pointer ``fleetslam/current/<robot>`` names; else ``<robot>/session.ckpt``)."""
    try:
        with stored_run(out, etcd) as store:
            state = store.load_checkpoint(robot)
            if isinstance(store, FencedStore):
                pointer = store.current(robot)
                where = "no pointer" if pointer is None else \
                    f"{pointer.file} (worker {pointer.worker}, ended {pointer.ended})"
            else:
                where = "session.ckpt" if state is not None else "none"
    except Exception as exc:  # a damaged or missing checkpoint is a finding, not a crash
        return {"checkpoint": f"unreadable: {exc}", "lost": len(report.get("acknowledged", [])),
                "checkpoint_keyframes": 0}
    kept = set() if state is None else {kf.frame_index for kf in state.tracking.map.keyframes}
    acked = set(report.get("acknowledged", []))
    return {"checkpoint": where, "checkpoint_keyframes": len(kept),
            "lost": len(acked - kept), "lost_indices": sorted(acked - kept)}


class Run:
    """One case under one placement: the processes, the schedule, the measurements."""

    def __init__(self, case: Case, placement: str, timing: Timing, out: Path) -> None:
        self.case, self.placement, self.timing, self.out = case, placement, timing, out
        self.logs = out / "logs"
        self.a_id, self.b_id = ("w0", "w1") if case.b_larger_id else ("w1", "w0")
        self.events: dict[str, float] = {}
        self.ended: dict[str, float] = {}  # worker -> when its process ended
        self.procs: dict[str, subprocess.Popen] = {}
        self.notes: list[str] = []
        self.robot_names: list[str] = []

    def _event(self, what: str, t: float | None = None) -> float:
        self.events[what] = time.time() if t is None else t
        print(f"  {what} at +{self.events[what] - self.events['start']:.1f} s", flush=True)
        return self.events[what]

    def execute(self) -> dict[str, Any]:
        self.out.mkdir(parents=True, exist_ok=False)
        self.events["start"] = time.time()
        load_before = os.getloadavg()
        link = NamespaceLink()
        etcd: EtcdService | None = None
        observer = client = None
        try:
            link.create()
            if self.placement == "etcd":
                etcd = EtcdService(self.out / "etcd", also_listen=(link.host_ip,)).start()
            port = free_endpoint().rsplit(":", 1)[1]
            host_ep, b_ep = f"tcp/127.0.0.1:{port}", f"tcp/{link.host_ip}:{port}"
            self.procs["router"] = start_router(f"tcp/0.0.0.0:{port}",
                                                self.logs / "router.log")
            coord_a = coord_b = []
            if etcd is not None:
                coord_a = ["--coordination", etcd.endpoint]
                coord_b = ["--coordination", f"http://{link.host_ip}:{etcd.client_port}"]
            self.procs[self.a_id] = start_worker(host_ep, self.a_id, self.out,
                                                 self.logs / f"{self.a_id}.log", extra=coord_a)
            self.procs[self.b_id] = start_worker(
                b_ep, self.b_id, self.out, self.logs / f"{self.b_id}.log", extra=coord_b,
                zenoh_config=str(_zenoh_config_without_shm(self.out / "zenoh-b.json")),
                prefix=link.prefix())
            client = CloudClient(host_ep, reach_deadline_s=self.timing.start_deadline_s)
            _await_workers(client, {self.a_id, self.b_id}, self.timing.start_deadline_s)
            observer = FeedbackObserver(host_ep)
            sources = self._sources()
            self.robot_names = list(sources)
            for name, source in sources.items():
                self.procs[name] = start_robot(
                    host_ep, name, source, 3, self.logs / f"{name}.log",
                    self.out / name / ROBOT_REPORT, extra=["--rate", self.timing.rate])
            self._event("robots started")
            self._schedule(link, observer)
            summary = self._merge(client)
        finally:
            if client is not None:
                client.close()
            self._stop_workers()
            if observer is not None:
                observer.close()
            for name, p in self.procs.items():
                if p.poll() is None:
                    p.kill()
                    p.wait()
            link.close()
        try:
            return self._measure(summary, observer, etcd, sources, link, load_before)
        finally:
            if etcd is not None:
                etcd.stop()

    def _sources(self) -> dict[str, str]:
        pieces = PIECES[:self.timing.robots]
        if self.timing.frames is not None:
            pieces = [f"{p.split('-')[0]}-{int(p.split('-')[0]) + self.timing.frames - 1}"
                      for p in pieces]
        return {f"r{i}": f"{SEVEN_SCENES}:{piece}" for i, piece in enumerate(pieces)}

    def _robots(self) -> dict[str, subprocess.Popen]:
        return {n: self.procs[n] for n in self.robot_names if n in self.procs}

    def _schedule(self, link: NamespaceLink, observer: FeedbackObserver) -> None:
        """Wait for the first feedback, then cut / shape, heal / stop / unshape on time, until
        every robot has exited."""
        t = self.timing
        deadline = time.monotonic() + t.start_deadline_s
        while observer.first_feedback() is None:
            self._robots_alive_or_raise(allow_done=False)
            if time.monotonic() > deadline:
                raise TimeoutError(f"no robot heard any feedback within {t.start_deadline_s:.0f}"
                                   f" s of starting (logs: {self.logs})")
            time.sleep(0.1)
        first = self._event("first feedback", observer.first_feedback())
        steps: list[tuple[float, str]] = [(first + t.cut_at_s, "cut")]
        if self.case.congest:
            steps = [(first + t.cut_at_s, "shape"), (first + t.cut_at_s + t.tbf_s, "unshape")]
        elif self.case.heal:
            steps.append((first + t.cut_at_s + t.heal_after_s, "heal"))
        if self.case.stop_b:
            steps.append((first + t.cut_at_s + t.stop_after_s, "stop B"))
        deadline = time.monotonic() + t.run_deadline_s
        while self._robots_alive_or_raise(allow_done=True) or steps:
            now = time.time()
            for w in (self.a_id, self.b_id):
                if self.procs[w].poll() is not None and w not in self.ended:
                    self.ended[w] = now  # its ownerships end with it
                    self.notes.append(f"worker {w} exited with {self.procs[w].returncode}")
            while steps and steps[0][0] <= now:
                _, step = steps.pop(0)
                if step == "cut":
                    self._event("cut", link.cut())
                elif step == "heal":
                    self._event("heal", link.heal())
                elif step == "shape":
                    self._event("shape", link.shape(t.tbf_rate))
                elif step == "unshape":
                    self._event("unshape", link.unshape())
                elif step == "stop B":
                    self.procs[self.b_id].terminate()
                    self._event("stop B")
            if time.monotonic() > deadline:
                raise TimeoutError(f"robots still running {t.run_deadline_s:.0f} s after the "
                                   f"first feedback (logs: {self.logs})")
            time.sleep(0.05)
        self._event("robots done")

    def _robots_alive_or_raise(self, allow_done: bool) -> bool:
        alive = False
        for name, p in self._robots().items():
            code = p.poll()
            if code is None:
                alive = True
            elif code != 0 and name not in self.ended:
                self.ended[name] = time.time()
                self.notes.append(f"robot {name} exited with {code}")
                print(f"  robot {name} exited with {code} (see {self.logs / (name + '.log')})",
                      flush=True)
            elif not allow_done and code == 0:
                raise RuntimeError(f"robot {name} ended before any feedback")
        return alive

    def _merge(self, client: CloudClient) -> dict[str, Any] | None:
        try:
            summary = client.merge(timeout=self.timing.merge_deadline_s)
            self._event("merged")
            return summary
        except (TimeoutError, RuntimeError) as exc:
            self.notes.append(f"merge failed: {exc}")
            print(f"  merge failed: {exc}", flush=True)
            return None

    def _stop_workers(self) -> None:
        """A lost machine never shuts down cleanly: B still cut off is SIGKILLed; the rest
        stop with SIGTERM (final checkpoints), all at once."""
        b = self.procs.get(self.b_id)
        if b is not None and b.poll() is None and "cut" in self.events \
                and "heal" not in self.events and not self.case.stop_b:
            b.kill()
            b.wait()
            self.ended[self.b_id] = time.time()
        workers = [w for w in (self.a_id, self.b_id) if w in self.procs]
        for w in workers:
            if self.procs[w].poll() is None:
                self.procs[w].terminate()
        for w in workers:
            try:
                self.procs[w].wait(30.0)
            except subprocess.TimeoutExpired:
                self.notes.append(f"worker {w} did not stop within 30 s of SIGTERM: killed")
                self.procs[w].kill()
                self.procs[w].wait()
            self.ended.setdefault(w, time.time())
        router = self.procs.get("router")
        if router is not None and router.poll() is None:
            router.terminate()
            try:
                router.wait(10.0)
            except subprocess.TimeoutExpired:
                router.kill()
                router.wait()

    def _measure(self, summary: dict[str, Any] | None, observer: FeedbackObserver | None,
                 etcd: EtcdService | None, sources: dict[str, str], link: NamespaceLink,
                 load_before: tuple[float, float, float]) -> dict[str, Any]:
        ivs = []
        for w in (self.a_id, self.b_id):
            ivs += ownership_log.intervals(self.logs / f"{w}.log", w, self.ended.get(w))
        overlaps = ownership_log.overlaps(ivs)
        cut = self.events.get("cut") or self.events.get("shape")
        robots: dict[str, Any] = {}
        for name in sources:
            report_path = self.out / name / ROBOT_REPORT
            report = json.loads(report_path.read_text()) if report_path.exists() else {}
            answered = observer.answered(name) if observer else {}
            owners_at_cut = ownership_log.owner_at(ivs, name, cut) if cut else []
            on_b = self.b_id in owners_at_cut
            failover = None
            if on_b and cut is not None:
                grants = [iv.start for iv in ivs if iv.robot == name and iv.worker == self.a_id
                          and iv.start > cut]
                if grants:
                    heard = observer.first_after(name, grants[0]) if observer else None
                    failover = None if heard is None else heard - cut
            ack = _acknowledged_lost(self.out, name, report,
                                     etcd.endpoint if etcd is not None else None)
            robots[name] = {
                "on_b_at_cut": on_b, "owners_at_cut": owners_at_cut,
                "failover_s": failover,
                "frames_sent": report.get("frames"),
                "frames_answered": len(answered),
                "frames_lost": (report["frames"] - len(answered)) if "frames" in report else None,
                "answered_twice": sum(1 for c in answered.values() if c > 1),
                "takeovers": report.get("takeovers"),
                "longest_pause_s": report.get("longest_feedback_gap_s"),
                "acknowledged": len(report.get("acknowledged", [])),
                "acknowledged_lost": ack["lost"], "checkpoint": ack["checkpoint"],
                "checkpoint_keyframes": ack["checkpoint_keyframes"],
                "grants": sum(1 for iv in ivs if iv.robot == name)}
        merge = None
        if summary is not None:
            sequences = {n: open_source(s) for n, s in sources.items()}
            summary.pop("outputs", None)
            score_fleet(summary, self.out, sequences)  # ground truth, read only now
            add_robot_reports(summary, self.out)
            m = summary.get("merge") or {}
            joint = (m.get("evaluation") or {}).get("joint_ate")
            merge = {"groups": ["+".join(g) for g in (m.get("components") or {}).values()],
                     "joint_ate_cm": 100 * joint["rmse_m"] if joint else None}
            for r in summary.get("robots", []):
                if r["name"] in robots and r.get("ate"):
                    robots[r["name"]]["ate_cm"] = 100 * r["ate"]["rmse_m"]
        return {
            "case": self.case.name, "placement": self.placement,
            "a": self.a_id, "b": self.b_id,
            "events_s": {k: round(v - self.events["start"], 3) for k, v in self.events.items()},
            "link_events": [(round(t - self.events["start"], 3), what)
                            for t, what in link.events],
            "robots": robots, "merge": merge,
            # After the cut, the longest the whole fleet heard no feedback at all.
            "fleet_silence_s": None if cut is None or observer is None else round(
                observer.longest_silence(cut, min(cut + 30.0, self.events["robots done"])), 3),
            "ownership": [{**asdict(iv), "start": round(iv.start - self.events["start"], 3),
                           "end": None if iv.end is None
                           else round(iv.end - self.events["start"], 3)} for iv in ivs],
            "fenced_s": {w: [round(t - self.events["start"], 3) for t in
                             ownership_log.fenced_at(self.logs / f"{w}.log", w)]
                         for w in (self.a_id, self.b_id)},
            "overlaps": [{"robot": o.robot, "workers": [o.first.worker, o.second.worker],
                          "seconds": round(o.seconds, 3)} for o in overlaps],
            "one_owner": not overlaps,
            "load_before": load_before, "load_after": os.getloadavg(),
            "notes": self.notes, "out": str(self.out)}


def _fmt(v: Any, digits: int = 1) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.{digits}f}"
    return str(v)


def table(result: dict[str, Any]) -> str:
    rows = []
    for name, r in result["robots"].items():
        rows.append([name, "B" if r["on_b_at_cut"] else "A", _fmt(r["failover_s"]),
                     r["frames_sent"], r["frames_lost"], r["answered_twice"], r["takeovers"],
                     _fmt(r["longest_pause_s"]), r["acknowledged"],
                     r["checkpoint_keyframes"], r["acknowledged_lost"], r["grants"],
                     _fmt(r.get("ate_cm"))])
    merge = result["merge"] or {}
    overlaps = ", ".join(f"{o['robot']} {'/'.join(o['workers'])} {o['seconds']} s"
                         for o in result["overlaps"])
    head = (f"{result['case']} [{result['placement']}] A={result['a']} B={result['b']}: "
            f"one owner at a time: {'yes' if result['one_owner'] else f'NO ({overlaps})'}"
            f"; merge groups {' | '.join(merge.get('groups', [])) or '-'}"
            f"; joint ATE {_fmt(merge.get('joint_ate_cm'))} cm"
            f"; no feedback to any robot for {_fmt(result['fleet_silence_s'])} s after the cut"
            f"; load {result['load_before'][0]:.1f} -> {result['load_after'][0]:.1f}")
    return head + "\n" + format_table(
        ["robot", "owner at cut", "failover s", "frames sent", "frames lost", "answered twice",
         "takeovers", "longest pause s", "KF acked", "KF in ckpt", "acked KF lost",
         "grants", "ATE cm"], rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cases", default=",".join(CASES),
                        help=f"comma-separated, of {', '.join(CASES)}")
    parser.add_argument("--placement", choices=PLACEMENTS, default="etcd")
    parser.add_argument("--runs", type=int, default=1, help="repeat every case")
    parser.add_argument("--rate", default=Timing.rate, help="each robot's frames per second")
    parser.add_argument("--frames", type=int, default=None,
                        help="frames per robot (default: the whole 200-frame piece)")
    parser.add_argument("--robots", type=int, default=Timing.robots, choices=range(1, 5))
    parser.add_argument("--cut-at", type=float, default=Timing.cut_at_s,
                        help="seconds after the first feedback")
    parser.add_argument("--heal-after", type=float, default=Timing.heal_after_s)
    parser.add_argument("--stop-after", type=float, default=Timing.stop_after_s)
    parser.add_argument("--tbf-rate", default=Timing.tbf_rate)
    parser.add_argument("--tbf-s", type=float, default=Timing.tbf_s)
    parser.add_argument("--out", default="bench/results/partition.json")
    args = parser.parse_args()
    # SIGTERM (a timeout, a Ctrl-C's sibling) unwinds like an exception: every `finally`
    # tears down its namespace and processes.
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    cases = [c.strip() for c in args.cases.split(",") if c.strip()]
    unknown = [c for c in cases if c not in CASES]
    if unknown:
        sys.exit(f"--cases: unknown {', '.join(unknown)} (known: {', '.join(CASES)})")
    if not SEVEN_SCENES.exists():
        sys.exit(f"{SEVEN_SCENES} missing: this benchmark needs ../shared/data")
    why = unavailable()
    if why:
        sys.exit(f"partition.py: {why}")
    removed = remove_leftovers()
    if removed:
        print(f"removed leftovers of a crashed run: {', '.join(removed)}")
    timing = Timing(cut_at_s=args.cut_at, heal_after_s=args.heal_after,
                    stop_after_s=args.stop_after, tbf_rate=args.tbf_rate, tbf_s=args.tbf_s,
                    rate=args.rate, frames=args.frames, robots=args.robots)
    out = Path(args.out)
    work = out.parent / "partition-runs" / time.strftime("%Y%m%d-%H%M%S")
    results = []
    for i in range(args.runs):
        for key in cases:
            print(f"{key} ({CASES[key].name}), {args.placement}, run {i} ...", flush=True)
            run = Run(CASES[key], args.placement, timing, work / f"{key}-{args.placement}-{i}")
            try:
                result = run.execute()
            except Exception as exc:
                print(f"  {key} failed: {exc}", flush=True)
                result = {"case": CASES[key].name, "placement": args.placement,
                          "error": str(exc), "out": str(run.out)}
            result["key"], result["run"] = key, i
            results.append(result)
            if "error" not in result:
                print(table(result), flush=True)
    out.parent.mkdir(parents=True, exist_ok=True)
    previous = json.loads(out.read_text()) if out.exists() else {}
    # One file for both placements and every case: a run replaces the earlier results of
    # its cases under its placement.
    kept = [r for r in previous.get("results", [])
            if (r.get("placement"), r.get("key")) not in {(args.placement, c) for c in cases}]
    out.write_text(json.dumps({
        "cores": os.cpu_count(), "pieces": PIECES, "timing": asdict(timing),
        "results": kept + results}, indent=2) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()

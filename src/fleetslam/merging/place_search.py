"""Inter-robot place search, the merger's heaviest step: for a robot's new keyframe, ask every
other robot's keyframe database for candidates and verify them geometrically
(inter_robot.py); then index the keyframe for the keyframes to come.

A search is asked for with ``submit`` and its result taken with ``take_results``, so the
merger never waits for one. ``PlaceSearch`` searches at once, in-line (one-process runs,
the tests). ``PlaceSearchProcess`` (the cloud's) runs a ``PlaceSearch`` in a process of its
own at a lower priority: the search holds Python's GIL for its numpy work and faiss's
search, so on the merger's thread it took the GIL from the robots tracking in the same
worker (measured: 21 % of that worker's GIL time with 8 robots at once, more than their
tracking). Niced, it may be starved on a busy machine: nobody waits for it (the merger's
thread only sends and takes what came back), and a keyframe that waited longer than
``merge.search_behind_s`` for its search is indexed at once and searched later, when the
search has nothing newer to do (``search_late``): a starved search catches up with the
robots first, and with its backlog once they give it time (measured: 13-30 of rk-3's 49
keyframes waited that long with three robots and the cloud on two cores). Both give the
same matches: a search is a function of the keyframes indexed before it.

If the process dies, or answers nothing for ``merge.search_timeout_s`` while a request
waits, the search goes on in-line from the keyframes kept here, and the log says so: a
failed helper must not end the merge. Silence, not the oldest request's age, is what counts:
with 20 robots on two saturated cores the process answered all along, niced, but its
backlog's oldest request passed 60 s; the search then went in-line, into the very worker
whose robots it was niced to spare (bench/worker_scaling.py, stop 54).

A search finds only what is indexed when it runs, so a pair of keyframes is compared by the
one that arrives second, against the other robot's map as it is then. Two things keep
whether two robots join from depending on which one started first:
- a pair is verified both ways (``verify_both_ways``): the geometric check is not
  symmetric (its matches, thresholds and refinement are the query's), and borderline true
  pairs pass in one direction only;
- each robot's keyframes are searched again in a robot not joined with it each time that
  robot's map has doubled (``catch-up``): a place found early in a small map ranks lower
  among the many keyframes of a robot that started earlier. Each pair is verified once.
Measured on redkitchen's three robots fed one robot after another: without these, r0
joined only when r1's keyframes came before r0's (3 of 6 orders).
"""

from __future__ import annotations

import collections
import logging
import multiprocessing
import os
import queue
import threading
import time
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from typing import TYPE_CHECKING, Any, Callable, Sequence

import numpy as np

from fleetslam.backend.place_recognition import ApproximateKeyframeDatabase, KeyframeDatabase
from fleetslam.backend.places import make_database
from fleetslam.backend.process_stats import process_cpu_seconds
from fleetslam.backend.workers import end_process, start_background
from fleetslam.camera import Camera
from fleetslam.config import Config
from fleetslam.merging.inter_robot import PlaceMatch, verify_counting, verify_places
from fleetslam.transforms import invert
from fleetslam.wire.merger_keyframes import KeyframeSummary

if TYPE_CHECKING:
    from fleetslam.backend.vocabulary import BowDatabase

log = logging.getLogger("fleetslam.merge")

# A silent search process counts as working if it used this much CPU since it last answered
# (a stopped or deadlocked one uses none; a tick is 10 ms).
MIN_PROGRESS_S = 0.05
# And it is given up all the same once silent this many merge.search_timeout_s.
BUSY_SILENCE_TIMEOUTS = 5


@dataclass
class Searched:
    """A keyframe's place search, done: what the merger takes (``MapMerger.take_matches``)."""

    summary: KeyframeSummary
    matches: list[PlaceMatch]
    seconds: float | None  # the search's time (None: no other robot was asked)
    searched: bool  # False: indexed, its search put off (it waited beyond search_behind_s)
    late: bool = False  # the put-off search of a keyframe indexed before


@dataclass
class _Robot:
    camera: Camera
    places: "KeyframeDatabase | ApproximateKeyframeDatabase | BowDatabase"
    keyframes: list[KeyframeSummary] = field(default_factory=list)
    # Per other robot: its keyframe count when all of this robot's keyframes were last
    # searched in it (the catch-up runs again once it has doubled).
    caught_up: dict[str, int] = field(default_factory=dict)


def verify_both_ways(query: KeyframeSummary, query_camera: Camera, place: KeyframeSummary,
                     place_camera: Camera, score: float, config: Config) -> PlaceMatch | None:
    """``verify_places`` with ``query`` as the query, else with ``place`` as the query (the
    match turned round): a pair's verdict does not depend on which keyframe came second.
    The second check is skipped when fewer descriptors matched than merge.min_refined_inliers
    (a quarter of the failures on redkitchen; none of them passed turned round)."""
    match, matched = verify_counting(query, query_camera, place, place_camera, score, config)
    if match is not None or matched < config.merge.min_refined_inliers:
        return match
    back = verify_places(place, place_camera, query, query_camera, score, config)
    if back is None:
        return None
    return PlaceMatch(query, place, invert(back.T_place_query), score, back.ransac_inliers,
                      back.inliers)


def pair_key(a: KeyframeSummary, b: KeyframeSummary) -> tuple[tuple[str, int], ...]:
    """Two keyframes as an unordered pair."""
    return tuple(sorted(((a.robot, a.keyframe), (b.robot, b.keyframe))))


class PlaceSearch:
    """Each robot's keyframes and their place database, searched in-line: ``submit``
    indexes, then searches (or puts the search off); ``idle`` does a put-off search;
    ``take_results`` hands the results over."""

    def __init__(self, config: Config) -> None:
        self.config = config
        self.robots: dict[str, _Robot] = {}
        self._done: list[Searched] = []
        # Keyframes indexed with their search put off: (summary, others, apart), in order.
        self._late: collections.deque = collections.deque()
        self._tried: set[tuple[tuple[str, int], ...]] = set()  # pairs verified already

    def start(self) -> None:
        """Nothing to start in-line (``PlaceSearchProcess`` starts its process)."""

    def close(self) -> None:
        """Nothing to end in-line."""

    @property
    def pending(self) -> int:
        """Searches put off and not done yet (``idle`` does them)."""
        return len(self._late)

    def idle(self) -> bool:
        """One put-off search, done now (the caller has nothing newer); False if none."""
        if not self._late:
            return False
        self._done.append(self.search_late())
        return True

    def add_robot(self, name: str, camera: Camera) -> None:
        if name not in self.robots:
            self.robots[name] = _Robot(camera, self._database())

    def _database(self) -> "KeyframeDatabase | ApproximateKeyframeDatabase | BowDatabase":
        pr, cfg = self.config.place_recognition, self.config.merge
        if cfg.place_index == "approximate" and pr.method == "nearest_neighbour":
            return ApproximateKeyframeDatabase(pr, cfg.place_index_exact_up_to,
                                               cfg.place_index_links, cfg.place_index_breadth)
        return make_database(pr)

    def submit(self, summary: KeyframeSummary, others: Sequence[str], asked: float,
               apart: Sequence[str] = ()) -> None:
        """Search ``summary`` in the robots ``others`` (asked at ``asked``, monotonic time);
        ``apart``: those of them not joined with its robot (the catch-up's)."""
        self._done.append(self.search(summary, others, asked, apart))

    def take_results(self) -> list[Searched]:
        done, self._done = self._done, []
        return done

    def search(self, summary: KeyframeSummary, others: Sequence[str], asked: float,
               apart: Sequence[str] = ()) -> Searched:
        """The verified matches of ``summary`` in the robots ``others`` (at most one per
        robot, in that order), then, once ``summary`` is indexed, those of the catch-up in
        its robot's map by the robots ``apart``. If it was asked more than search_behind_s
        ago, it is only indexed, and its search put off (``search_late``)."""
        self.index(summary)  # its own robot's map: its search looks in the others'
        if time.monotonic() - asked > self.config.merge.search_behind_s:
            if others:
                self.put_off(summary, others, apart)
            return Searched(summary, [], None, False)
        return self._search(summary, others, apart, late=False)

    def put_off(self, summary: KeyframeSummary, others: Sequence[str],
                apart: Sequence[str]) -> None:
        """``summary`` (indexed already) to be searched later."""
        self._late.append((summary, list(others), list(apart)))

    def search_late(self) -> Searched:
        """The oldest put-off search, done now, in the maps as they are now (pairs verified
        since from the other side are not verified again)."""
        return self._search(*self._late.popleft(), late=True)

    def _search(self, summary: KeyframeSummary, others: Sequence[str], apart: Sequence[str],
                late: bool) -> Searched:
        start = time.perf_counter()
        matches = [m for other in others if (m := self._find_place(summary, other)) is not None]
        matches += self._catch_up(summary.robot, apart)
        seconds = time.perf_counter() - start if others else None
        return Searched(summary, matches, seconds, True, late)

    def index(self, summary: KeyframeSummary) -> None:
        robot = self.robots[summary.robot]
        robot.keyframes.append(summary)
        robot.places.add(summary.keyframe, summary.features.descriptors)

    def _catch_up(self, name: str, apart: Sequence[str]) -> list[PlaceMatch]:
        """Every keyframe of each robot in ``apart`` searched again in robot ``name``'s map,
        if that map has doubled since they last were."""
        size = len(self.robots[name].places)
        matches: list[PlaceMatch] = []
        for other_name in apart:
            other = self.robots[other_name]
            if size < 2 * other.caught_up.get(name, 0):
                continue
            other.caught_up[name] = size
            matches += [m for kf in other.keyframes
                        if (m := self._find_place(kf, name)) is not None]
        return matches

    def _find_place(self, query: KeyframeSummary, other_name: str) -> PlaceMatch | None:
        """The first of the other robot's top candidates that verifies, of those not
        verified with ``query`` before."""
        other = self.robots[other_name]
        if not len(other.places):
            return None
        camera = self.robots[query.robot].camera
        for candidate in other.places.query(query.features.descriptors,
                                            top_k=self.config.merge.candidates):
            place = other.keyframes[candidate.key]
            if (key := pair_key(query, place)) in self._tried:
                continue
            self._tried.add(key)
            match = verify_both_ways(query, camera, place, other.camera, candidate.score,
                                     self.config)
            if match is not None:
                return match
        return None


# A match as it crosses the pipe: (query robot, query keyframe, place robot, place keyframe,
# T_place_query, score, RANSAC inliers, refined inliers); the keyframes themselves are on
# both sides already.
Found = tuple[str, int, str, int, np.ndarray, float, int, int]


def _serve(conn: Connection, config: Config, parent_pid: int) -> None:
    """The search process: requests from ``conn`` in order, until None or the cloud is
    gone, and the put-off searches while none waits; each keyframe's answer: (robot,
    keyframe, matches found, seconds, searched, late)."""
    start_background(parent_pid, 0)  # niced by the cloud as it started (see _start)
    search = PlaceSearch(config)
    while True:
        try:
            if search.pending and not conn.poll(0):
                _send(conn, search.search_late())
                continue
            request = conn.recv()
        except (EOFError, OSError):  # the cloud is gone (killed: the pipe is reset)
            return
        if request is None:
            return
        kind, payload = request
        if kind == "robot":
            search.add_robot(*payload)
        elif kind == "keyframe":
            _send(conn, search.search(*payload))


def _send(conn: Connection, s: Searched) -> None:
    found: list[Found] = [(m.query.robot, m.query.keyframe, m.place.robot, m.place.keyframe,
                           m.T_place_query, m.score, m.ransac_inliers, m.inliers)
                          for m in s.matches]
    conn.send((s.summary.robot, s.summary.keyframe, found, s.seconds, s.searched, s.late))


@dataclass
class _Request:
    summary: KeyframeSummary
    others: list[str]
    asked: float
    apart: list[str]
    sent: float  # when it went to the process (its deadline runs from here)


class PlaceSearchProcess:
    """A ``PlaceSearch`` in its own process at niceness ``nice`` (see the module's
    docstring). Used from one thread (the merger's), which ``wake`` is called for when an
    answer is in; a thread sends the requests and one takes the answers, so that thread
    never waits on the process. ``close`` from any thread."""

    def __init__(self, config: Config, nice: int, timeout_s: float,
                 wake: Callable[[], None] = lambda: None) -> None:
        self.config = config
        self.nice = nice
        self.timeout_s = timeout_s
        self._wake = wake
        self._conn: Connection | None = None
        self._process: multiprocessing.process.BaseProcess | None = None
        self._sender: threading.Thread | None = None
        self._outbox: queue.Queue = queue.Queue()
        # The process's answers and failures, from the reader thread.
        self._answers: collections.deque = collections.deque()
        # What the process was told, to rebuild the search in-line if it fails.
        self._robots: list[tuple[str, Camera]] = []
        self._keyframes: dict[str, list[KeyframeSummary]] = {}
        self._requests: dict[tuple[str, int], _Request] = {}  # unanswered, in order
        self._late: dict[tuple[str, int], _Request] = {}  # answered, their search put off
        self._inline: PlaceSearch | None = None
        self._closed = False
        self._answered_at = 0.0  # when the process last answered (monotonic)
        # The process's CPU seconds when it last answered or was last excused, and when it
        # was: a silent process that kept working meanwhile is starved, not hung.
        self._cpu_mark = 0.0
        self._excused_at = 0.0

    @property
    def inline(self) -> bool:
        return self._inline is not None

    @property
    def pending(self) -> int:
        """Searches asked for and not taken yet, put-off ones too (the merger's drain waits
        for them)."""
        if self._inline is not None:
            return self._inline.pending
        return len(self._requests) + len(self._late)

    def idle(self) -> bool:
        """The process does its put-off searches itself; in-line, one of them."""
        return self._inline.idle() if self._inline is not None else False

    def start(self) -> None:
        """Start the process now (the cloud does, as it starts), not at the first robot."""
        if self._conn is not None or self._closed or self._inline is not None:
            return
        parent, child = multiprocessing.get_context("spawn").Pipe()
        process = multiprocessing.get_context("spawn").Process(
            target=_serve, args=(child, self.config, os.getpid()),
            name="fleetslam-place-search", daemon=True)
        try:
            process.start()
        except OSError as exc:
            return self._fail(f"it could not be started ({exc})")
        # Niced from its first instruction, not once its imports are done: a second of
        # start-up CPU at tracking's priority made this worker look busy to placement.
        try:
            os.setpriority(os.PRIO_PROCESS, process.pid,
                           min(19, os.getpriority(os.PRIO_PROCESS, 0) + self.nice))
        except (AttributeError, OSError):  # not Linux, or gone already
            pass
        child.close()
        self._conn, self._process = parent, process
        self._sender = threading.Thread(target=self._send_all, args=(parent,),
                                        name="place-search-send", daemon=True)
        self._sender.start()
        threading.Thread(target=self._read_all, args=(parent,), name="place-search-read",
                         daemon=True).start()

    def _send_all(self, conn: Connection) -> None:
        while (message := self._outbox.get()) is not None:
            try:
                conn.send(message)
            except (OSError, ValueError) as exc:
                self._answer(("failed", f"it could not be reached ({exc!r})"))
                return
        try:
            conn.send(None)
        except (OSError, ValueError):
            pass

    def _read_all(self, conn: Connection) -> None:
        while True:
            try:
                answer = conn.recv()
            except (EOFError, OSError) as exc:
                self._answer(("failed", f"it ended ({exc!r})"))
                return
            self._answer(answer)

    def _answer(self, answer: Any) -> None:
        self._answered_at = time.monotonic()
        process = self._process
        if process is not None:
            self._cpu_mark = process_cpu_seconds(process.pid) or self._cpu_mark
        if not self._closed and self._inline is None:
            self._answers.append(answer)
            self._wake()

    def add_robot(self, name: str, camera: Camera) -> None:
        if name in self._keyframes:
            return
        self._robots.append((name, camera))
        self._keyframes[name] = []
        if self._inline is not None:
            self._inline.add_robot(name, camera)
        else:
            self.start()
            self._outbox.put(("robot", (name, camera)))

    def submit(self, summary: KeyframeSummary, others: Sequence[str], asked: float,
               apart: Sequence[str] = ()) -> None:
        self._keyframes[summary.robot].append(summary)
        if self._inline is not None:
            return self._inline.submit(summary, others, asked, apart)
        if self._closed:
            return
        self.start()
        self._requests[(summary.robot, summary.keyframe)] = _Request(
            summary, list(others), asked, list(apart), time.monotonic())
        self._outbox.put(("keyframe", (summary, list(others), asked, list(apart))))

    def take_results(self) -> list[Searched]:
        """The searches answered since the last call, in order; a failed process (dead, or
        silent for timeout_s while a request waits) turns the search in-line here."""
        out: list[Searched] = []
        while self._answers and self._inline is None:
            answer = self._answers.popleft()
            if answer[0] == "failed":
                self._fail(answer[1])
                break
            robot, keyframe, found, seconds, searched, late = answer
            if late:
                request = self._late.pop((robot, keyframe))
            else:
                request = self._requests.pop((robot, keyframe))
                if not searched and request.others:
                    self._late[(robot, keyframe)] = request
            out.append(Searched(request.summary, [
                PlaceMatch(self._keyframes[query][qk], self._keyframes[place][pk], T, score,
                           ransac, n)
                for query, qk, place, pk, T, score, ransac, n in found], seconds, searched,
                late))
        if self._requests and self._inline is None and not self._closed:
            silent_since = max(next(iter(self._requests.values())).sent, self._answered_at)
            now = time.monotonic()
            if now - max(silent_since, self._excused_at) > self.timeout_s \
                    and not self._working(now - silent_since):
                self._fail(f"no answer for {now - silent_since:.0f} s "
                           f"(merge.search_timeout_s {self.timeout_s:.0f} s)")
        if self._inline is not None:
            out += self._inline.take_results()
        return out

    def _working(self, silent_s: float) -> bool:
        """Whether a process silent for ``silent_s`` used the CPU since it last answered (or
        was last excused): a niced search on cores the workers' tracking fills is starved,
        not hung, and stays (measured: 60 s without an answer while 20 robots saturated 2
        cores, bench/worker_scaling.py), up to BUSY_SILENCE_TIMEOUTS timeouts of silence."""
        process = self._process
        cpu = None if process is None else process_cpu_seconds(process.pid)
        if cpu is None or cpu - self._cpu_mark < MIN_PROGRESS_S \
                or silent_s > BUSY_SILENCE_TIMEOUTS * self.timeout_s:
            return False
        if self._excused_at <= self._answered_at:  # said once a silence
            log.warning("the merger's place search process: no answer for %.0f s, working "
                        "meanwhile (%.1f CPU s): starved, waiting for it", silent_s,
                        cpu - self._cpu_mark)
        self._cpu_mark, self._excused_at = cpu, time.monotonic()
        return True

    def _fail(self, reason: str) -> None:
        """Search in-line from now on: rebuilt from the keyframes answered (the put-off
        searches still to do), then the unanswered ones searched in turn (those asked too
        long ago only indexed, and put off)."""
        if self._closed or self._inline is not None:
            return
        log.error("the merger's place search process: %s; searching in-line from now on",
                  reason)
        self._stop_process()
        unanswered = {id(r.summary) for r in self._requests.values()}
        search = PlaceSearch(self.config)
        for name, camera in self._robots:
            search.add_robot(name, camera)
            for kf in self._keyframes[name]:
                if id(kf) not in unanswered:
                    search.index(kf)
        for r in self._late.values():
            search.put_off(r.summary, r.others, r.apart)
        self._late = {}
        self._answers.clear()
        self._inline = search
        requests, self._requests = self._requests, {}
        for r in requests.values():
            search.submit(r.summary, r.others, r.asked, r.apart)

    def _stop_process(self) -> None:
        conn, process, self._conn, self._process = self._conn, self._process, None, None
        sender, self._sender = self._sender, None
        self._outbox.put(None)  # the sender's last message: the process's end
        if process is not None:
            end_process(process, 2.0)
        if sender is not None:  # a send blocked on a stopped process fails once it is gone
            sender.join(2.0)
        if conn is not None:
            conn.close()

    def close(self) -> None:
        """End the process (from any thread: searches not answered yet are dropped)."""
        self._closed = True
        self._stop_process()


Searcher = PlaceSearch | PlaceSearchProcess

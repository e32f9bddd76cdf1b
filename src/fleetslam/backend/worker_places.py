"""A session's keyframe database kept in its worker process, so that a loop query sends the
keyframes added since the last one (a delta), not the whole database.

The parent side, ``PlaceMirror``, records what its session's worker has been sent and turns
each query into a ``PlaceRequest``: the entries added since (appended in order: a keyframe
database only grows at its end), or the whole database the first time and whenever the
worker says its copy does not match (``reseed``). The worker side, ``answer``, keeps one copy
per session in its process (the least recently queried dropped beyond ``keep``: a session
that ended without saying so) and answers the query against it; ``forget`` drops a copy at
the session's end. The copy is built by the same ``add`` calls as the session's own, so a
query gives what the in-line query gives.

A request is pickled here, once, so its bytes are counted exactly (``PlaceMirror.sent_bytes``).
"""

from __future__ import annotations

import pickle
import time
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any, Hashable

import numpy as np

from fleetslam.backend.state import PlaceDatabase


@dataclass
class PlaceRequest:
    session: str
    # Entries the worker's copy must hold before ``adds`` (its version).
    base: int
    adds: list[tuple[Hashable, np.ndarray]]
    # The whole database (then ``base`` is 0 and ``adds`` empty): a first or a reseed.
    full: PlaceDatabase | None
    descriptors: np.ndarray
    allowed: np.ndarray


class PlaceMirror:
    """What one session's worker holds of its keyframe database (see the module's
    docstring). ``added`` is called with every entry the session adds, in order."""

    def __init__(self, session: str) -> None:
        self.session = session
        self.sent = 0  # entries the worker has been sent
        self.seeded = False
        # Entries added since ``sent`` (their arrays are the keyframes' own: not copies).
        self.log: list[tuple[Hashable, np.ndarray]] = []
        self.sent_bytes: list[int] = []
        self.full_sends = 0

    def added(self, key: Hashable, descriptors: np.ndarray) -> None:
        self.log.append((key, descriptors))

    def request(self, frozen: PlaceDatabase, descriptors: np.ndarray, allowed: np.ndarray
                ) -> bytes:
        """The query against ``frozen`` (the database as it was at the keyframe: its first
        ``len(frozen)`` entries), as the bytes to send."""
        n = len(frozen)
        if n < self.sent:
            raise ValueError(f"a query against {n} entries after {self.sent} were sent")
        fresh, self.log = self.log[:n - self.sent], self.log[n - self.sent:]
        if self.seeded and len(fresh) == n - self.sent:
            request = PlaceRequest(self.session, self.sent, fresh, None, descriptors, allowed)
        else:
            request = PlaceRequest(self.session, 0, [], frozen, descriptors, allowed)
            self.full_sends += 1
        self.sent, self.seeded = n, True
        blob = pickle.dumps(request, protocol=pickle.HIGHEST_PROTOCOL)
        self.sent_bytes.append(len(blob))
        return blob

    def reseed(self) -> None:
        """The worker's copy is missing or differs: the next request sends it whole."""
        self.seeded = False


# -- in the worker process -----------------------------------------------------------------

# Each session's copy, least recently queried first.
_copies: OrderedDict[str, PlaceDatabase] = OrderedDict()
# How many copies this process keeps (loop_closing.worker_databases, set by its initialiser).
_keep: dict[str, int] = {}


def keep_databases(n: int) -> None:
    _keep["databases"] = n


def answer(blob: bytes) -> tuple[list[Any] | None, float]:
    """In a worker: (candidates, seconds) of a ``PlaceRequest``; candidates None when this
    process's copy is not at the request's base (the caller sends the whole database)."""
    start = time.perf_counter()
    request: PlaceRequest = pickle.loads(blob)
    if request.full is not None:
        database = request.full
    else:
        database = _copies.pop(request.session, None)  # re-inserted below: most recent
        if database is None or len(database) != request.base:
            return None, time.perf_counter() - start
        for key, descriptors in request.adds:
            database.add(key, descriptors)
        if len(database) != len(request.allowed):
            return None, time.perf_counter() - start  # a delta missed: dropped, sent whole
    _copies[request.session] = database
    _copies.move_to_end(request.session)
    while len(_copies) > _keep.get("databases", len(_copies)):
        _copies.popitem(last=False)
    candidates = database.query(request.descriptors, request.allowed)
    return candidates, time.perf_counter() - start


def forget(session: str) -> None:
    """In a worker: the session ended; its copy goes."""
    _copies.pop(session, None)


def held() -> dict[str, int]:
    """In a worker: the sessions whose copies it keeps, and their entries (tests)."""
    return {session: len(database) for session, database in _copies.items()}

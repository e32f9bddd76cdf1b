"""Place recognition over keyframes: which stored keyframes show the place a new one shows.

One component, used for loops within a robot (backend/loop_closing.py), relocalisation and
matches across robots (merging/merger.py). Every
keyframe's ORB descriptors go into the database; a query looks up each of its descriptors'
nearest neighbours (Hamming, faiss's exact binary index) among the entries it may match,
and every entry holding a near neighbour gets a vote. A descriptor whose neighbours are
spread over many entries (a generic corner) says little, so its vote is weighted by an
inverse document frequency, log(1 + allowed entries / entries it hits), as a bag of words
would weight a common word.

No vocabulary is needed: the index is exact and built on the fly from the allowed entries
(a copy of their descriptors, a few MB for a few hundred keyframes), so the candidates never
depend on images seen elsewhere. The alternative, a bag of words on a vocabulary trained
with ``fleetslam vocabulary``, is ``vocabulary.BowDatabase`` (``[place_recognition]
method = "bag_of_words"``); bench/place_recognition.py compares the two.

The database is plain numpy (picklable with the session); faiss objects live only inside
``query``.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from typing import Hashable

import faiss
import numpy as np

from fleetslam.backend.state import PlaceDatabase
from fleetslam.config import PlaceRecognitionConfig


DESCRIPTOR_BITS = 256
# One thread: a query is a few tens of ms, and faiss's OpenMP threads spin against the
# other sessions and stages sharing the cores (measured: 55 ms alone, 0.3-1.1 s with the
# default threads while another process held a core; 60-200 ms with one).
faiss.omp_set_num_threads(1)


@dataclass
class PlaceCandidate:
    entry: int  # database entry (insertion order)
    key: Hashable  # what the caller stored with it (e.g. a keyframe id)
    score: float  # idf-weighted votes per query descriptor
    votes: int  # query descriptors with a near neighbour in this entry


@dataclass
class KeyframeDatabase:
    config: PlaceRecognitionConfig
    keys: list[Hashable] = field(default_factory=list)
    descriptors: np.ndarray = field(default_factory=lambda: np.zeros((0, 32), np.uint8))
    # Entry of every stored descriptor row.
    owner: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))

    def __len__(self) -> int:
        return len(self.keys)

    def add(self, key: Hashable, descriptors: np.ndarray) -> int:
        """Store one keyframe's descriptors (N x 32 uint8); returns its entry number."""
        entry = len(self.keys)
        self.keys.append(key)
        d = np.ascontiguousarray(descriptors, dtype=np.uint8).reshape(-1, 32)
        self.descriptors = np.vstack([self.descriptors, d])
        self.owner = np.concatenate([self.owner, np.full(len(d), entry, np.int64)])
        return entry

    def query(self, descriptors: np.ndarray, allowed: np.ndarray | None = None,
              top_k: int | None = None) -> list[PlaceCandidate]:
        """Entries most similar to ``descriptors``, best first, among ``allowed`` (bool per
        entry; all if None). At most ``top_k`` (config default), each scoring at least
        ``min_score_ratio`` of the best."""
        cfg = self.config
        n_entries = len(self.keys)
        allowed = query_scope(n_entries, allowed, descriptors)
        if allowed is None:
            return []
        rows = np.flatnonzero(allowed[self.owner])
        if not len(rows):
            return []
        index = faiss.IndexBinaryFlat(DESCRIPTOR_BITS)
        index.add(self.descriptors[rows])
        k = min(cfg.neighbours, len(rows))
        dist, nn = index.search(np.ascontiguousarray(descriptors, dtype=np.uint8), k)
        near = (dist <= cfg.max_hamming) & (nn >= 0)
        entry = np.where(near, self.owner[rows[np.maximum(nn, 0)]], -1)
        score, votes = idf_votes(entry, n_entries, int(allowed.sum()))
        return best_candidates(self.keys, score, votes, cfg, top_k)


class ApproximateKeyframeDatabase:
    """The same votes as KeyframeDatabase, exact while it holds at most ``exact_up_to``
    entries, then over approximate neighbours: a graph index (faiss's binary HNSW) built
    from what it holds and grown with each keyframe, so a query costs about the log of the
    stored descriptors, not all of them. For the merger, which asks every other robot's map
    at each keyframe and never restricts the entries (no ``allowed``). Measured on redkitchen
    (150 keyframes' descriptors, 145k rows, efSearch 64): a query 42 ms against 244 ms exact,
    the exact top-1 among its top 3 in 145 of 150 queries; but below about a hundred entries
    the exact search is the cheaper (bench/merge_fleet.py: 20-51 against 36-80 ms a query,
    the same joins)."""

    def __init__(self, config: PlaceRecognitionConfig, exact_up_to: int,
                 links: int, breadth: int) -> None:
        self.config = config
        self.exact_up_to, self.links, self.breadth = exact_up_to, links, breadth
        self.exact: KeyframeDatabase | None = KeyframeDatabase(config)
        self.keys: list[Hashable] = self.exact.keys
        self.index: faiss.IndexBinaryHNSW | None = None
        self._owner: list[np.ndarray] = []  # rows' entries added since the last query
        self._owner_rows = np.zeros(0, np.int64)

    def __len__(self) -> int:
        return len(self.keys)

    def add(self, key: Hashable, descriptors: np.ndarray) -> int:
        if self.exact is not None:
            entry = self.exact.add(key, descriptors)
            if len(self.exact) > self.exact_up_to:
                self._to_graph()
            return entry
        entry = len(self.keys)
        self.keys.append(key)
        d = np.ascontiguousarray(descriptors, dtype=np.uint8).reshape(-1, 32)
        assert self.index is not None
        self.index.add(d)
        self._owner.append(np.full(len(d), entry, np.int64))
        return entry

    def _to_graph(self) -> None:
        assert self.exact is not None
        self.index = faiss.IndexBinaryHNSW(DESCRIPTOR_BITS, self.links)
        self.index.hnsw.efSearch = self.breadth
        self.index.add(self.exact.descriptors)
        self._owner_rows = self.exact.owner
        self.exact = None

    def query(self, descriptors: np.ndarray, allowed: np.ndarray | None = None,
              top_k: int | None = None) -> list[PlaceCandidate]:
        if allowed is not None:
            raise ValueError("an approximate place index answers for all its entries: "
                             "use KeyframeDatabase to restrict them")
        if self.exact is not None:
            return self.exact.query(descriptors, top_k=top_k)
        assert self.index is not None
        n_entries = len(self.keys)
        if not len(descriptors):
            return []
        if self._owner:
            self._owner_rows = np.concatenate([self._owner_rows, *self._owner])
            self._owner = []
        cfg = self.config
        k = min(cfg.neighbours, int(self.index.ntotal))
        dist, nn = self.index.search(np.ascontiguousarray(descriptors, dtype=np.uint8), k)
        near = (dist <= cfg.max_hamming) & (nn >= 0)
        entry = np.where(near, self._owner_rows[np.maximum(nn, 0)], -1)
        score, votes = idf_votes(entry, n_entries, n_entries)
        return best_candidates(self.keys, score, votes, cfg, top_k)


def idf_votes(entry: np.ndarray, n_entries: int, n_allowed: int
              ) -> tuple[np.ndarray, np.ndarray]:
    """Per entry, its idf-weighted score and its votes, from each query descriptor's
    neighbours' entries (rows; -1: no near neighbour). One vote per (query descriptor,
    entry), however many of its neighbours the entry holds (one landmark seen twice in one
    keyframe is still one landmark)."""
    entry = np.sort(entry, axis=1)
    fresh = np.ones_like(entry, bool)
    fresh[:, 1:] = entry[:, 1:] != entry[:, :-1]
    fresh &= entry >= 0
    hits = fresh.sum(axis=1)
    idf = np.log1p(n_allowed / np.maximum(hits, 1))
    q, c = np.nonzero(fresh)
    votes = np.bincount(entry[q, c], minlength=n_entries)
    score = np.bincount(entry[q, c], weights=idf[q], minlength=n_entries) / len(entry)
    return score, votes


def query_scope(n_entries: int, allowed: np.ndarray | None, descriptors: np.ndarray
                ) -> np.ndarray | None:
    """The entries a query may return (bool per entry; all if ``allowed`` is None), or None
    when there is nothing to search or nothing to search with."""
    if allowed is None:
        allowed = np.ones(n_entries, bool)
    if not n_entries or not allowed.any() or not len(descriptors):
        return None
    return allowed


def best_candidates(keys: list[Hashable], score: np.ndarray, votes: np.ndarray,
                    config: PlaceRecognitionConfig, top_k: int | None) -> list[PlaceCandidate]:
    """Entries by score, best first: at most ``top_k`` (config default), each scoring more
    than 0 and at least ``min_score_ratio`` of the best."""
    top_k = config.top_k if top_k is None else top_k
    order = np.argsort(-score, kind="stable")
    order = order[score[order] > 0][:top_k]
    if not len(order):
        return []
    best = score[order[0]]
    return [PlaceCandidate(int(e), keys[e], float(score[e]), int(votes[e]))
            for e in order if score[e] >= config.min_score_ratio * best]


def snapshot(database: PlaceDatabase) -> PlaceDatabase:
    """The database as it is now, unchanged by later ``add`` calls: both kinds append to
    ``keys`` in place but replace their arrays rather than write into them, so only the
    key list is copied (not megabytes of descriptors, on the tracking thread)."""
    frozen = copy.copy(database)
    frozen.keys = list(database.keys)
    return frozen

"""A binary bag-of-words vocabulary for ORB descriptors, and the keyframe database on it.

The vocabulary is a tree (DBoW2's layout): ``branching`` clusters per node, ``levels``
deep, clustered by k-majority (k-means with Hamming distance; a centre is the bitwise
majority of its members). A descriptor's word is the leaf it reaches going down the tree,
always to the nearest child. Each word weighs its inverse document frequency over the
training images, so a word every image has says little.

``BowDatabase`` stores each keyframe as a tf-idf weighted, L1-normalised word histogram
and scores a query against the stored keyframes with DBoW2's L1 score,
1 - |v/|v| - w/|w||_1 / 2 in [0, 1]; it answers as ``KeyframeDatabase`` does (same
candidates, filters and config), so place recognition can use either
(``[place_recognition] method``).
"""

from __future__ import annotations

import functools
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Hashable

import cv2
import numpy as np

from fleetslam.backend.place_recognition import PlaceCandidate, best_candidates, query_scope
from fleetslam.config import Config, PlaceRecognitionConfig
from fleetslam.datasets.tum import read_file_list
from fleetslam.pipeline.front_end import Describe, Extract, FrontEndState
from fleetslam.pipeline.states import CapturedFrame


DESCRIPTOR_BYTES = 32
_POPCOUNT = np.array([bin(i).count("1") for i in range(256)], np.uint8)
# Rows per block when measuring distances, to bound the N x k x 32 temporary.
_BLOCK = 65536
FORMAT = "fleetslam-orb-vocabulary"
VERSION = 1


def hamming(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamming distances between a (N, 32) and b (N, k, 32) row by row: (N, k)."""
    return _POPCOUNT[np.bitwise_xor(a[:, None, :], b)].sum(axis=2, dtype=np.int32)


def majority(descriptors: np.ndarray) -> np.ndarray:
    """The bitwise majority of descriptors (n, 32): the k-majority centre."""
    bits = np.unpackbits(descriptors, axis=1)
    return np.packbits(bits.mean(axis=0) > 0.5)


def _cluster(descriptors: np.ndarray, k: int, rng: np.random.Generator, rounds: int
             ) -> tuple[np.ndarray, np.ndarray]:
    """k-majority clustering with k-means++ seeding: (centres (k, 32), label per row)."""
    n = len(descriptors)
    centres = [descriptors[rng.integers(n)]]
    nearest = hamming(descriptors, np.asarray(centres)[None].repeat(n, 0))[:, 0]
    for _ in range(1, k):
        weights = nearest.astype(np.float64) ** 2
        if weights.sum() == 0:
            break  # fewer distinct descriptors than clusters
        centres.append(descriptors[rng.choice(n, p=weights / weights.sum())])
        d = hamming(descriptors, centres[-1][None, None].repeat(n, 0))[:, 0]
        nearest = np.minimum(nearest, d)
    C = np.asarray(centres)
    labels = np.full(n, -1)
    for _ in range(rounds):
        new = _nearest(descriptors, C)
        if np.array_equal(new, labels):
            break
        labels = new
        C = np.asarray([majority(descriptors[labels == j]) if (labels == j).any() else C[j]
                        for j in range(len(C))])
    return C, labels


def _nearest(descriptors: np.ndarray, centres: np.ndarray) -> np.ndarray:
    out = np.empty(len(descriptors), np.int64)
    for s in range(0, len(descriptors), _BLOCK):
        block = descriptors[s:s + _BLOCK]
        out[s:s + _BLOCK] = hamming(block, np.broadcast_to(
            centres, (len(block), *centres.shape))).argmin(axis=1)
    return out


@dataclass
class Vocabulary:
    """The tree: node 0 is the root; ``children[i]`` are node i's children (-1: none), a
    node without children is a word (``word[i]``, -1 for inner nodes)."""

    centres: np.ndarray  # (nodes, 32) uint8
    children: np.ndarray  # (nodes, branching) int64
    word: np.ndarray  # (nodes,) int64
    idf: np.ndarray  # (words,) float64
    trained_on: str = ""

    @property
    def n_words(self) -> int:
        return len(self.idf)

    @staticmethod
    def train(images: Iterable[np.ndarray], branching: int = 10, levels: int = 4,
              rounds: int = 10, seed: int = 0, trained_on: str = "") -> "Vocabulary":
        """Cluster the descriptors of ``images`` (one (n, 32) array per image) into a tree
        and weigh its words by their inverse document frequency over those images."""
        per_image = [np.ascontiguousarray(d, np.uint8).reshape(-1, DESCRIPTOR_BYTES)
                     for d in images]
        per_image = [d for d in per_image if len(d)]
        if not per_image:
            raise ValueError("no descriptors to train a vocabulary on")
        if branching < 2 or levels < 1:
            raise ValueError(f"a vocabulary needs branching >= 2 and levels >= 1, got "
                             f"{branching} and {levels}")
        data = np.vstack(per_image)
        rng = np.random.default_rng(seed)
        centres = [majority(data)]
        children: list[list[int]] = [[]]
        # Breadth first: (node, rows of data under it, depth).
        todo = [(0, np.arange(len(data)), 0)]
        while todo:
            node, rows, depth = todo.pop(0)
            if depth == levels or len(rows) <= branching:
                continue
            C, labels = _cluster(data[rows], branching, rng, rounds)
            for j in range(len(C)):
                members = rows[labels == j]
                if not len(members):
                    continue
                children[node].append(len(centres))
                centres.append(C[j])
                children.append([])
                todo.append((len(centres) - 1, members, depth + 1))
        table = np.full((len(centres), branching), -1, np.int64)
        for i, c in enumerate(children):
            table[i, :len(c)] = c
        leaf = table[:, 0] < 0
        word = np.full(len(centres), -1, np.int64)
        word[leaf] = np.arange(int(leaf.sum()))
        vocabulary = Vocabulary(np.asarray(centres, np.uint8), table, word,
                                np.zeros(int(leaf.sum())), trained_on)
        seen = np.zeros(vocabulary.n_words)
        for d in per_image:
            seen[np.unique(vocabulary.words(d))] += 1
        vocabulary.idf = np.log(len(per_image) / np.maximum(seen, 1))
        return vocabulary

    def words(self, descriptors: np.ndarray) -> np.ndarray:
        """The word of each descriptor (N, 32): down the tree to the nearest child."""
        d = np.ascontiguousarray(descriptors, np.uint8).reshape(-1, DESCRIPTOR_BYTES)
        node = np.zeros(len(d), np.int64)
        while True:
            kids = self.children[node]  # (N, branching)
            inner = kids[:, 0] >= 0
            if not inner.any():
                return self.word[node]
            rows = np.flatnonzero(inner)
            k = kids[rows]
            dist = hamming(d[rows], self.centres[np.maximum(k, 0)])
            dist[k < 0] = np.iinfo(np.int32).max
            node[rows] = k[np.arange(len(rows)), dist.argmin(axis=1)]

    def bow(self, descriptors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """tf-idf weighted, L1-normalised histogram: (sorted word ids, weights)."""
        if not len(descriptors):
            return np.zeros(0, np.int64), np.zeros(0)
        ids, counts = np.unique(self.words(descriptors), return_counts=True)
        weights = counts / counts.sum() * self.idf[ids]
        total = weights.sum()
        return ids, weights / total if total > 0 else weights

    def save(self, path: str | Path) -> None:
        np.savez_compressed(Path(path), format=np.array(FORMAT), version=np.array(VERSION),
                            centres=self.centres, children=self.children, word=self.word,
                            idf=self.idf, trained_on=np.array(self.trained_on))

    @staticmethod
    def load(path: str | Path) -> "Vocabulary":
        """A vocabulary :meth:`save` wrote; ValueError naming the file for anything else."""
        try:
            with np.load(Path(path), allow_pickle=False) as z:
                if str(z["format"]) != FORMAT or int(z["version"]) != VERSION:
                    raise ValueError(f"not a version {VERSION} {FORMAT} file")
                v = Vocabulary(z["centres"], z["children"], z["word"], z["idf"],
                               str(z["trained_on"]))
        except (OSError, KeyError, ValueError, EOFError) as exc:
            raise ValueError(f"{path}: not a vocabulary: {exc}") from exc
        nodes = len(v.centres)
        if (v.centres.dtype != np.uint8 or v.centres.shape[1:] != (DESCRIPTOR_BYTES,)
                or v.children.shape[0] != nodes or v.word.shape != (nodes,)
                or v.children.max(initial=-1) >= nodes
                or v.word.max(initial=-1) != len(v.idf) - 1 or not np.isfinite(v.idf).all()):
            raise ValueError(f"{path}: not a vocabulary: inconsistent tables")
        return v


@functools.lru_cache(maxsize=4)
def load_vocabulary(path: str) -> Vocabulary:
    """One copy per file for every session of a process."""
    return Vocabulary.load(path)


@dataclass
class BowDatabase:
    """Keyframes as bag-of-words vectors; the same interface as ``KeyframeDatabase``."""

    config: PlaceRecognitionConfig
    keys: list[Hashable] = field(default_factory=list)
    # Every stored (entry, word, weight), entries in insertion order.
    words: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    weights: np.ndarray = field(default_factory=lambda: np.zeros(0))
    owner: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))

    def __post_init__(self) -> None:
        if not self.config.vocabulary:
            raise ValueError("place_recognition.method = 'bag_of_words' needs "
                             "place_recognition.vocabulary (a file from `fleetslam vocabulary`)")
        load_vocabulary(self.config.vocabulary)  # a bad file fails now, not at a query

    @property
    def vocabulary(self) -> Vocabulary:
        return load_vocabulary(self.config.vocabulary)

    def __len__(self) -> int:
        return len(self.keys)

    def add(self, key: Hashable, descriptors: np.ndarray) -> int:
        entry = len(self.keys)
        self.keys.append(key)
        ids, w = self.vocabulary.bow(descriptors)
        self.words = np.concatenate([self.words, ids])
        self.weights = np.concatenate([self.weights, w])
        self.owner = np.concatenate([self.owner, np.full(len(ids), entry, np.int64)])
        return entry

    def query(self, descriptors: np.ndarray, allowed: np.ndarray | None = None,
              top_k: int | None = None) -> list[PlaceCandidate]:
        n_entries = len(self.keys)
        allowed = query_scope(n_entries, allowed, descriptors)
        if allowed is None:
            return []
        q_words, q_weights = self.vocabulary.bow(descriptors)
        at = np.searchsorted(q_words, self.words)
        at = np.minimum(at, len(q_words) - 1)
        common = (q_words[at] == self.words) & allowed[self.owner]
        if not common.any():
            return []
        v, w = q_weights[at[common]], self.weights[common]
        owner = self.owner[common]
        # DBoW2's L1 score over the words both vectors hold.
        score = 0.5 * np.bincount(owner, weights=v + w - np.abs(v - w), minlength=n_entries)
        votes = np.bincount(owner, minlength=n_entries)
        return best_candidates(self.keys, score, votes, self.config, top_k)



def training_images(folder: str | Path, every: int = 1) -> list[Path]:
    """The colour images of a folder, every ``every``-th: those listed in ``rgb.txt`` (TUM
    layout, 7-Scenes with index files), else its .png/.jpg files but depth images (7-Scenes'
    ``*.color.*``, a plain image folder), sorted by name."""
    root = Path(folder)
    if not root.is_dir():
        raise ValueError(f"{root}: no such image folder")
    if (root / "rgb.txt").exists():
        paths = [root / name for _, name in read_file_list(root / "rgb.txt")]
    else:
        # Depth images beside the colour ones (7-Scenes' .depth.png, x_depth.png) are not
        # training images.
        paths = sorted(p for p in root.iterdir()
                       if p.suffix.lower() in (".png", ".jpg", ".jpeg")
                       and not p.stem.lower().endswith("depth"))
    if not paths:
        raise ValueError(f"{root}: holds no colour images (.png/.jpg, or an rgb.txt)")
    return paths[::max(1, every)]


def image_descriptors(path: Path, config: Config) -> np.ndarray:
    """ORB descriptors of one colour image, extracted as the robots extract them."""
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise ValueError(f"{path}: cannot decode as a colour image")
    session = FrontEndState(config, None)  # type: ignore[arg-type]  # no camera needed
    rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
    depth = np.zeros(rgb.shape[:2], np.float32)
    state = Describe()(Extract()(CapturedFrame(0, 0.0, rgb, depth), session), session)
    return state.descriptors

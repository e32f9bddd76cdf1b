"""Place recognition alone, two ways: the exact binary nearest-neighbour index with
per-keyframe votes (faiss; the default) and a bag of words on a trained vocabulary
(DBoW2-style tree and L1 score, ``fleetslam vocabulary``). Ground truth only scores.

    .venv/bin/python bench/place_recognition.py [--out bench/results/place_recognition.json]

Each sequence's vocabulary is trained on images the sequence does not hold: redkitchen's
on TUM fr1_rpy (every 5th frame) + fr2_desk (10 frames), fr1_rpy's on redkitchen (every
5th frame); "same" rows use a vocabulary trained on the sequence itself (every 5th
frame), an upper bound no user gets.

1. Keyframes (bench/loop_closure.py's protocol): the final keyframes of one loop-closing
   run; each queries the keyframes >= 100 frames older; top-1 against ground-truth
   revisits (30 cm, 20 deg), before and after geometric verification.
2. Frames: every 2nd frame queries a database of every 2nd frame >= 100 frames older (more
   queries than there are keyframes); top-1 precision and recall with no score threshold,
   average precision over the top-1 score (ranked queries), query time.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from fleetslam.config import Config, PlaceRecognitionConfig
from fleetslam.datasets.tum import RgbdSequence
from fleetslam.backend.place_recognition import KeyframeDatabase
from fleetslam.backend.vocabulary import (
    BowDatabase,
    Vocabulary,
    image_descriptors,
    training_images,
)
from fleetslam.tables import format_table
from loop_closure import (
    REVISIT_MIN_FRAME_GAP,
    config_for,
    gt_revisits,
    place_recognition,
    track_session,
)
from shared_data import DATA, SEQUENCES, present_sequences

FRAME_STEP = 2
TRAIN_EVERY = 5
FR2_DESK = DATA / "tum_fr2_desk_slambook2_frames" / "loop10"


def train(folders: list[Path], path: Path, config: Config) -> dict[str, Any]:
    images = [p for f in folders for p in training_images(f, TRAIN_EVERY if f != FR2_DESK else 1)]
    start = time.perf_counter()
    descriptors = [image_descriptors(p, config) for p in images]
    extract_s = time.perf_counter() - start
    start = time.perf_counter()
    pr = config.place_recognition
    vocabulary = Vocabulary.train(descriptors, pr.vocabulary_branching, pr.vocabulary_levels,
                                  trained_on=", ".join(str(f) for f in folders))
    vocabulary.save(path)
    return {"path": str(path), "trained_on": [str(f) for f in folders], "images": len(images),
            "descriptors": int(sum(len(d) for d in descriptors)), "words": vocabulary.n_words,
            "extract_s": extract_s, "train_s": time.perf_counter() - start}


def average_precision(scores: np.ndarray, correct: np.ndarray, positives: int) -> float | None:
    """Area under precision-recall of the queries ranked by their top-1 score."""
    if not positives:
        return None
    order = np.argsort(-scores, kind="stable")
    hits = correct[order].astype(np.float64)
    precision = np.cumsum(hits) / np.arange(1, len(hits) + 1)
    return float((precision * hits).sum() / positives)


def frames_protocol(folder: Path, databases: dict[str, Any], config: Config) -> dict[str, Any]:
    seq = RgbdSequence(folder)
    frames = np.arange(0, len(seq), FRAME_STEP)
    descriptors = [image_descriptors(seq.rgb_paths[i], config) for i in frames]
    gt = seq.gt_poses[frames]
    revisit = gt_revisits(gt) & (np.abs(frames[:, None] - frames[None]) >= REVISIT_MIN_FRAME_GAP)
    out: dict[str, Any] = {"frames": len(frames)}
    for label, db in databases.items():
        add_ms = []
        for i, d in zip(frames, descriptors):
            start = time.perf_counter()
            db.add(int(i), d)
            add_ms.append(1000 * (time.perf_counter() - start))
        scores, correct, returned, query_ms, positives = [], [], 0, [], 0
        for q in range(len(frames)):
            allowed = frames <= frames[q] - REVISIT_MIN_FRAME_GAP
            if not allowed.any() or not np.isfinite(gt[q]).all():
                continue
            positive = bool(revisit[q, allowed].any())
            positives += positive
            start = time.perf_counter()
            found = db.query(descriptors[q], allowed, top_k=1)
            query_ms.append(1000 * (time.perf_counter() - start))
            if found:
                returned += 1
                scores.append(found[0].score)
                correct.append(bool(revisit[q, found[0].entry]))
        tp = int(np.sum(correct))
        out[label] = {
            "queries": len(query_ms), "positives": positives, "returned": returned,
            "true_positives": tp, "precision": tp / returned if returned else None,
            "recall": tp / positives if positives else None,
            "average_precision": average_precision(np.array(scores), np.array(correct),
                                                   positives),
            "query_ms_median": float(np.median(query_ms)), "query_ms_p95":
                float(np.percentile(query_ms, 95)), "add_ms_median": float(np.median(add_ms))}
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="bench/results/place_recognition.json")
    args = parser.parse_args()
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    config = Config()
    sequences = dict(present_sequences())
    if len(sequences) < 2:
        raise SystemExit("needs both sequences (each one's vocabulary is trained on the other)")
    other = {"7scenes_redkitchen_0-599": [SEQUENCES["tum_fr1_rpy_0-149"], FR2_DESK],
             "tum_fr1_rpy_0-149": [SEQUENCES["7scenes_redkitchen_0-599"]]}
    vocabularies: dict[str, dict[str, Any]] = {}
    for name, folder in sequences.items():
        vocabularies[name] = {
            "cross": train(other[name], out.parent / f"vocabulary-{name}-cross.npz", config),
            "same": train([folder], out.parent / f"vocabulary-{name}-same.npz", config)}

    def databases(name: str) -> dict[str, Any]:
        pr = config.place_recognition
        return {"nearest_neighbour": KeyframeDatabase(pr)} | {
            f"bag_of_words ({kind})": BowDatabase(PlaceRecognitionConfig(
                **{**pr.__dict__, "method": "bag_of_words",
                   "vocabulary": vocabularies[name][kind]["path"]}))
            for kind in ("cross", "same")}

    keyframes: dict[str, dict[str, Any]] = {}
    frames: dict[str, dict[str, Any]] = {}
    for name, folder in sequences.items():
        tracked = track_session(folder, config_for(True))
        keyframes[name] = {label: place_recognition(name, folder, tracked, db)
                           for label, db in databases(name).items()}
        frames[name] = frames_protocol(folder, databases(name), config)

    print("vocabularies (10 x 4 tree)")
    print(format_table(["for sequence", "kind", "trained on", "images", "descriptors", "words",
                        "train s"],
                       [[n, k, "; ".join(Path(f).name for f in v["trained_on"]), v["images"],
                         v["descriptors"], v["words"], v["train_s"]]
                        for n, kinds in vocabularies.items() for k, v in kinds.items()]))
    print(f"\n1. keyframes: top-1 among keyframes >= {REVISIT_MIN_FRAME_GAP} frames older, "
          "before / after verification")
    print(format_table(
        ["sequence", "method", "queries", "positives", "TP", "P", "R", "TP ver", "P ver",
         "R ver", "bad pose", "query ms", "p95"],
        [[n, label, p["queries"], p["positives"], p["true_positives_before"],
          p["precision_before"], p["recall_before"], p["true_positives_after"],
          p["precision_after"], p["recall_after"], p["verified_with_wrong_pose"],
          p["query_time"]["median_ms"], p["query_time"]["p95_ms"]]
         for n, methods in keyframes.items() for label, p in methods.items()]))
    print(f"\n2. frames: every {FRAME_STEP}nd frame against every {FRAME_STEP}nd frame >= "
          f"{REVISIT_MIN_FRAME_GAP} frames older, top-1, no score threshold")
    print(format_table(
        ["sequence", "method", "queries", "positives", "TP", "P", "R", "AP", "query ms",
         "p95", "add ms"],
        [[n, label, r["queries"], r["positives"], r["true_positives"], r["precision"],
          r["recall"], r["average_precision"], r["query_ms_median"], r["query_ms_p95"],
          r["add_ms_median"]]
         for n, f in frames.items() for label, r in f.items() if isinstance(r, dict)]))
    for p in keyframes.values():
        for r in p.values():
            r.pop("per_query", None)
    out.write_text(json.dumps({"vocabularies": vocabularies, "keyframes": keyframes,
                               "frames": frames}, indent=1, default=float))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()

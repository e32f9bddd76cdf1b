"""The paper's per-frame message: an OpenCV FileStorage YAML file (our reading of the paper:
shared/paper-notes.md §1, outside this repository).

    %YAML:1.0
    KeyPoint: [[x, y, size, angle, response, octave, class_id], ...]
    Depth: [metres per keypoint, ...]
    Descriptor: !!opencv-matrix (rows N, cols 32, dt u)
    Time: seconds

Kept for compatibility and inspection, and as the size baseline the binary wire format
must beat; OpenCV reads it back (``cv2.FileStorage``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from fleetslam.pipeline.states import FeatureFrame


@dataclass
class PaperMessage:
    keypoints: np.ndarray  # N x 7 float, KEYPOINT_COLUMNS
    depth: np.ndarray  # N float, metres
    descriptors: np.ndarray  # N x 32 uint8
    time: float


def _write(fs: cv2.FileStorage, features: FeatureFrame) -> None:
    fs.startWriteStruct("KeyPoint", cv2.FileNode_SEQ)
    for row in features.keypoints.astype(np.float64):
        fs.startWriteStruct("", cv2.FileNode_SEQ | cv2.FileNode_FLOW)
        for value in row[:5]:
            fs.write("", float(value))
        fs.write("", int(row[5]))  # octave
        fs.write("", int(row[6]))  # class_id
        fs.endWriteStruct()
    fs.endWriteStruct()
    fs.startWriteStruct("Depth", cv2.FileNode_SEQ | cv2.FileNode_FLOW)
    for value in features.depth.astype(np.float64):
        fs.write("", float(value))
    fs.endWriteStruct()
    fs.write("Descriptor", np.ascontiguousarray(features.descriptors, dtype=np.uint8))
    fs.write("Time", float(features.timestamp))


def paper_yaml_bytes(features: FeatureFrame) -> bytes:
    """The message as the paper stored it, in memory."""
    fs = cv2.FileStorage(".yml", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY)
    _write(fs, features)
    text = fs.releaseAndGetString()
    # OpenCV 5 heads its YAML "%YAML 1.2"; the paper's files (OpenCV 3/4) say "%YAML:1.0",
    # which every OpenCV reads. Same body either way.
    if text.startswith("%YAML 1.2"):
        text = "%YAML:1.0" + text[len("%YAML 1.2"):]
    return text.encode()


def write_paper_yaml(path: str | Path, features: FeatureFrame) -> None:
    Path(path).write_bytes(paper_yaml_bytes(features))


def read_paper_yaml(path: str | Path) -> PaperMessage:
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: no such message file")
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except cv2.error as exc:
        raise ValueError(f"{path}: not an OpenCV YAML file: {exc}") from exc
    try:
        kp_node, depth_node = fs.getNode("KeyPoint"), fs.getNode("Depth")
        desc_node, time_node = fs.getNode("Descriptor"), fs.getNode("Time")
        missing = [name for name, node in (("KeyPoint", kp_node), ("Depth", depth_node),
                                           ("Descriptor", desc_node), ("Time", time_node))
                   if node.empty()]
        if missing:
            raise ValueError(f"{path}: message lacks {', '.join(missing)}")
        keypoints = np.array([[kp_node.at(i).at(j).real() for j in range(7)]
                              for i in range(kp_node.size())]).reshape(-1, 7)
        depth = np.array([depth_node.at(i).real() for i in range(depth_node.size())])
        descriptors = desc_node.mat()
        descriptors = np.zeros((0, 32), np.uint8) if descriptors is None else descriptors
        if not (len(keypoints) == len(depth) == len(descriptors)):
            raise ValueError(f"{path}: {len(keypoints)} keypoints, {len(depth)} depths and "
                             f"{len(descriptors)} descriptors do not match")
        return PaperMessage(keypoints, depth, descriptors.astype(np.uint8), time_node.real())
    finally:
        fs.release()

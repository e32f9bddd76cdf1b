"""Structure-aware fuzzing of checkpoint restoring: mutations of real session checkpoints,
each restored as a cloud worker restores one (``CloudStore.load_checkpoint``: the file's
size, the .npz, the tree, the session's shape).

    .venv/bin/python bench/fuzz_checkpoint.py [--cases 3000] [--seed 0] [--frames 20]
        [--out bench/results/fuzz_checkpoint.json]
    .venv/bin/python bench/fuzz_checkpoint.py --replay FAMILY:INDEX   (one case, traceback)

Seeds: the checkpoint of a session that tracked the first ``--frames`` frames of TUM
fr1_rpy (keyframes, landmarks, place database), and of a session as a hello opens it.

Families (case i of a family is generated from (seed, family, i)):
- truncate: the file cut anywhere.
- bytes: 1-16 bytes flipped or set anywhere (zip directory, .npy headers, data, JSON).
- tree: the JSON tree edited where the decoder reads it, re-sealed (a valid zip): a node
  replaced by a value of another type (string, huge or negative int, NaN, list, object,
  another class, an array reference that is missing or used twice, deep nesting), an
  attribute dropped or added.
- array: a referenced array replaced, re-sealed: a row dropped or added, transposed,
  another dtype, indices huge or negative.
- zip: the archive rebuilt with compressed members (a deflated zip bomb among them),
  a duplicated member, a member's .npy header edited.

A case ends in a clean refusal (CheckpointError naming the file), or the session is
restored, and then it must track a frame (a restored session that fails when used is a
finding too). Anything else escaping is a finding, with its reproducer.

Seed 0, 5000 cases, 20 frames (2 shared cores): at first (load 3-4.3) 4598 refused
cleanly, 399 restored and tracking, 3 restored that failed at their first frame on values
the types allow (the checkpoint's own ``tracking.local_map_scope`` "x", ``orb.scale_factor``
1, camera ``cx`` 1e308); with the config's ranges and the camera's principal point checked,
2 more (an ``orb.n_features`` past a C int, a uint64 index array numpy's bincount refuses);
with those checked too (load 1.0-2.0): 4629 refused, 371 restored and tracking, 0
findings; slowest case 0.49 s; peak RSS 204 MB (194 MB of it the set-up's tracking); zip
bombs of 64-256 MB refused unread.
"""

from __future__ import annotations

import argparse
import io
import json
import random
import resource
import tempfile
import time
import traceback
import warnings
import zipfile
from pathlib import Path
from typing import Any, Callable

import numpy as np

from fleetslam.backend.back_end import new_state
from fleetslam.backend.robot_slam import RobotSlam
from fleetslam.cloud.session.session_state import SessionState, TrajectoryRow, capture
from fleetslam.cloud.session.store import CHECKPOINT, CloudStore
from fleetslam.config import Config
from fleetslam.datasets.tum import RgbdSequence
from fleetslam.pipeline.states import CapturedFrame
from fleetslam.transport.protocol import Hello
from fleetslam.wire.data_tree import CheckpointError

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "tum_fr1_rpy_f000-149"
FAMILIES = ("truncate", "bytes", "tree", "array", "zip")


def seeds(frames: int, data: Path = DATA) -> tuple[list[bytes], Any, CapturedFrame]:
    """Two checkpoints (a tracked session, a new one), the camera and the next frame."""
    seq = RgbdSequence(data)
    captured = [CapturedFrame(f.index, f.timestamp, f.rgb, f.depth_m)
                for f, _ in zip(seq, range(frames + 1))]
    pipeline = RobotSlam.new(Config(), seq.camera)
    rows = []
    for frame in captured[:frames]:
        out = pipeline.track(frame)
        rows.append(TrajectoryRow(out.index, out.timestamp, out.T_world_camera, out.tracked,
                                  out.is_keyframe, out.reference_keyframe,
                                  out.T_reference_camera))
    hello = Hello(3, seq.camera, "fuzz")
    tracked = SessionState("r0", hello, pipeline.state, pipeline.front_end, frames - 1,
                           frames - 1, rows, cloud_ms=[1.0] * frames)
    fresh = SessionState("r0", hello, new_state(Config(), seq.camera))
    return [capture(tracked).to_bytes(), capture(fresh).to_bytes()], seq.camera, captured[-1]


# -- the archive as parts, and back ---------------------------------------------------------

def parts(blob: bytes) -> tuple[Any, dict[str, bytes]]:
    """The tree (parsed) and every other member's .npy bytes."""
    with zipfile.ZipFile(io.BytesIO(blob)) as z:
        members = {i.filename[:-4]: z.read(i) for i in z.infolist()}
    tree = members.pop("__tree__")
    return json.loads(np.load(io.BytesIO(tree)).tobytes()), members


def npy(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, array)
    return buffer.getvalue()


def seal(tree: Any, members: dict[str, bytes], compression: int = zipfile.ZIP_STORED,
         text: str | None = None) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression) as z:
        z.writestr("__tree__.npy", npy(np.frombuffer(
            (text if text is not None else json.dumps(tree)).encode(), np.uint8)))
        for name, data in members.items():
            z.writestr(f"{name}.npy", data)
    return buffer.getvalue()


def nodes(tree: Any) -> list[tuple[Any, Any]]:
    """Every (container, key) of the tree, iteratively."""
    out, stack = [], [tree]
    while stack:
        node = stack.pop()
        keys = range(len(node)) if isinstance(node, list) else \
            list(node) if isinstance(node, dict) else []
        for k in keys:
            out.append((node, k))
            stack.append(node[k])
    return out


# -- mutations ------------------------------------------------------------------------------

def truncate(rng: random.Random, blob: bytes, _: Any) -> bytes:
    return blob[:rng.randrange(len(blob))]


def flip_bytes(rng: random.Random, blob: bytes, _: Any) -> bytes:
    data = bytearray(blob)
    for _ in range(rng.randint(1, 16)):
        i = rng.randrange(len(data))
        data[i] = rng.randrange(256) if rng.random() < 0.5 else data[i] ^ (1 << rng.randrange(8))
    return bytes(data)


def edit_tree(rng: random.Random, blob: bytes, parsed: Any) -> bytes:
    tree, members = json.loads(json.dumps(parsed[0])), dict(parsed[1])
    container, key = rng.choice(nodes(tree))
    arrays = list(members)
    choice = rng.randrange(12)
    if choice == 0:
        container[key] = "x" * rng.choice([0, 1, 1000])
    elif choice == 1:
        container[key] = rng.choice([-1, 0, 1, 2**31, -2**63, 10**30, 10**4000 // 10**3990])
    elif choice == 2:
        container[key] = rng.choice([float("nan"), float("inf"), -0.0, 1e308])
    elif choice == 3:
        container[key] = rng.choice([[], [1, 2], [[[]]], {}])
    elif choice == 4:
        container[key] = {"__obj__": rng.choice(["Hello", "Keyframe", "LocalMap", "Config",
                                                 "Popen"]), "attributes": {}}
    elif choice == 5:
        container[key] = {"__nd__": rng.choice(arrays + ["missing", 7])}
    elif choice == 6:  # deep nesting in the state, beside what is there
        depth = rng.choice([50, 70, 1000, 100_000])
        text = json.dumps(tree).replace('"state": ', '"state": ' + "[" * depth + "0"
                                        + "]" * depth + ', "x": ', 1)
        return seal(None, members, text=text)
    elif choice == 7 and isinstance(container, dict):
        del container[key]
    elif choice == 8 and isinstance(container, dict):
        container[rng.choice(["extra", "predict_pose", "__class__", "track"])] = 1
    elif choice == 9:
        container[key] = {rng.choice(["__bytes__", "__counter__", "__dict__", "__tuple__"]):
                          rng.choice(["zz", [[1]], [[[], 1]], 5, None, [[1, 2, 3]]])}
    elif choice == 10:
        container[key] = None
    else:
        container[key] = True
    return seal(tree, members)


def edit_array(rng: random.Random, blob: bytes, parsed: Any) -> bytes:
    tree, members = parsed[0], dict(parsed[1])
    name = rng.choice(list(members))
    array = np.load(io.BytesIO(members[name]))
    choice = rng.randrange(7)
    if choice == 0 and array.ndim and len(array):
        array = array[:-1]
    elif choice == 1:
        array = np.concatenate([array, array[:1]]) if array.ndim and len(array) else \
            np.zeros((3,) + array.shape[1:], array.dtype)
    elif choice == 2:
        array = array.T
    elif choice == 3:
        array = array.astype(rng.choice([np.float32, np.int8, np.uint64, bool, np.complex64]))
    elif choice == 4 and array.dtype.kind in "iu" and array.size:
        array = array.copy()
        info = np.iinfo(array.dtype)  # an index far out of range, either way
        array.flat[rng.randrange(array.size)] = rng.choice([info.min, info.max,
                                                            max(info.min, -5)])
    elif choice == 5:
        array = array.reshape(-1)
    else:
        array = np.zeros(rng.choice([(0,), (4, 4), (3, 3), (2, 32)]))
    members[name] = npy(array)
    return seal(tree, members)


def edit_zip(rng: random.Random, blob: bytes, parsed: Any) -> bytes:
    tree, members = parsed[0], dict(parsed[1])
    choice = rng.randrange(5)
    if choice == 0:
        return seal(tree, members, rng.choice([zipfile.ZIP_DEFLATED, zipfile.ZIP_BZIP2,
                                               zipfile.ZIP_LZMA]))
    if choice == 1:  # a deflated bomb: 64-256 MB of zeros in place of one array
        name = rng.choice(list(members))
        n = rng.choice([64, 256]) << 20
        buffer = io.BytesIO()
        with zipfile.ZipFile(buffer, "w") as z:
            z.writestr("__tree__.npy", npy(np.frombuffer(json.dumps(tree).encode(), np.uint8)))
            for other, data in members.items():
                if other != name:
                    z.writestr(f"{other}.npy", data)
            info = zipfile.ZipInfo(f"{name}.npy")
            info.compress_type = zipfile.ZIP_DEFLATED
            with z.open(info, "w", force_zip64=True) as m:
                m.write(npy_header(n))
                chunk = bytes(1 << 22)
                for _ in range(n >> 22):
                    m.write(chunk)
        return buffer.getvalue()
    if choice == 2:  # a member twice
        return appended(tree, members, rng.choice(list(members)))
    name = rng.choice(list(members))
    data = bytearray(members[name])
    header_end = min(len(data), 128)
    for _ in range(rng.randint(1, 4)):
        data[rng.randrange(6, header_end)] = rng.choice(b"0123456789(),' {}<>|fiuOVS")
    members[name] = bytes(data)
    return seal(tree, members)


def npy_header(n: int) -> bytes:
    """The .npy header of n bytes (uint8)."""
    buffer = io.BytesIO()
    np.lib.format.write_array_header_1_0(buffer, {"descr": "|u1", "fortran_order": False,
                                                  "shape": (n,)})
    return buffer.getvalue()


def appended(tree: Any, members: dict[str, bytes], name: str) -> bytes:
    """The archive with member ``name`` written a second time."""
    buffer = io.BytesIO(seal(tree, members))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with zipfile.ZipFile(buffer, "a") as z:
            z.writestr(f"{name}.npy", members[name])
    return buffer.getvalue()


MUTATORS: dict[str, Callable[[random.Random, bytes, Any], bytes]] = {
    "truncate": truncate, "bytes": flip_bytes, "tree": edit_tree, "array": edit_array,
    "zip": edit_zip}


# -- running --------------------------------------------------------------------------------

def case(family: str, index: int, seed: int, blobs: list[bytes], parsed: list[Any]) -> bytes:
    rng = random.Random(f"{seed}/{family}/{index}")
    which = rng.randrange(len(blobs))
    return MUTATORS[family](rng, blobs[which], parsed[which])


def run_case(data: bytes, folder: Path, camera: Any, frame: CapturedFrame) -> str:
    """'refused', 'restored' (and it tracked a frame), or raises what escaped."""
    (folder / "r0" / CHECKPOINT).write_bytes(data)
    try:
        state = CloudStore(folder).load_checkpoint("r0")
    except CheckpointError as exc:
        if str(folder / "r0" / CHECKPOINT) not in str(exc):
            raise AssertionError(f"refusal without the file: {exc}") from None
        return "refused"
    pipeline = RobotSlam(state.tracking.config, state.hello.camera,
                       front_end=state.front_end, state=state.tracking)
    with np.errstate(all="ignore"):  # a mutated value may be odd yet valid: no noise
        pipeline.track(frame)
    return "restored"


def rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def fuzz(blobs: list[bytes], camera: Any, frame: CapturedFrame, cases: int, seed: int
         ) -> dict[str, Any]:
    """Run ``cases`` cases, the families in turn; what came of them."""
    parsed = [parts(b) for b in blobs]
    outcomes: dict[str, dict[str, int]] = {f: {} for f in FAMILIES}
    findings: list[dict[str, Any]] = []
    slowest = (0.0, "")
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        (folder / "r0").mkdir()
        for i in range(cases):
            family = FAMILIES[i % len(FAMILIES)]
            index = i // len(FAMILIES)
            data = case(family, index, seed, blobs, parsed)
            start = time.perf_counter()
            try:
                outcome = run_case(data, folder, camera, frame)
            except Exception as exc:  # noqa: BLE001 - every escape is a finding
                outcome = "escaped"
                findings.append({"case": f"{family}:{index}", "error": repr(exc)[:300],
                                 "where": traceback.format_exc().splitlines()[-3][:200]})
            took = time.perf_counter() - start
            slowest = max(slowest, (took, f"{family}:{index}"))
            outcomes[family][outcome] = outcomes[family].get(outcome, 0) + 1
    return {"cases": cases, "outcomes": outcomes, "non_clean": len(findings),
            "findings": findings[:50], "slowest_s": round(slowest[0], 3),
            "slowest_case": slowest[1], "peak_rss_mb": round(rss_mb(), 1)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--cases", type=int, default=3000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--frames", type=int, default=20)
    parser.add_argument("--out", type=Path)
    parser.add_argument("--replay")
    args = parser.parse_args()
    blobs, camera, frame = seeds(args.frames)
    print(f"seeds: {[len(b) for b in blobs]} bytes; peak RSS after set-up {rss_mb():.0f} MB")
    if args.replay:
        family, index = args.replay.split(":")
        data = case(family, int(index), args.seed, blobs, [parts(b) for b in blobs])
        with tempfile.TemporaryDirectory() as tmp:
            (Path(tmp) / "r0").mkdir()
            print(run_case(data, Path(tmp), camera, frame))
        return
    result = fuzz(blobs, camera, frame, args.cases, args.seed)
    print(json.dumps(result, indent=2))
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()

"""Structure-aware fuzzing of every decoder the cloud runs on untrusted bytes.

    .venv/bin/python bench/fuzz_wire.py [--cases 100000] [--seed 0] [--workers 2]
        [--out bench/results/fuzz_wire.json]
    .venv/bin/python bench/fuzz_wire.py --replay FAMILY:SEED:INDEX   (one case, with traceback)

Seed messages are real: a few 7-Scenes frames through the robot's edge stages, sealed at
every split point (PNG and JPEG images, with and without zstd), keyframe uploads, feedback,
and every control message the protocol's builders make. Each case mutates one seed and runs
the cloud's whole decode path on it: ``open_message`` and the payload decoder of the
message's channel with its content checks (frames, keyframes; feedback is what a robot
decodes), or ``parse_control`` and the parser of the message's type. A clean rejection is a
WireError (binary messages) or a ValueError (control messages: the servers catch that);
anything else escaping, or a case slower than ``--slow-s``, is a finding, with its
reproducer (family, seed, case index).

Families (each case is one family; its generator is seeded by (seed, family, index)):
- payload: bit flips, byte sets, truncation, insertion, deletion, duplicated ranges, splices,
  and edits of the very fields the decoder reads (counts, lengths, modes, floats) to 0, 1,
  the maximum, a huge or negative value; re-sealed with ``seal``, so the CRC is valid.
- header: version, kind, split point, flags, robot id, seq, timestamp, raw and wire lengths,
  magic, CRC; with a recomputed CRC or the old one.
- raw: random bytes, truncated and extended seeds, random payloads in a valid envelope.
- zstd_bomb: small zstd frames that expand to up to 4x the payload limit (zeros, or a real
  payload whose count field was set huge, padded with zeros), with true, lying and missing
  sizes, corrupted or concatenated frames.
- image_bomb: a message's image replaced by PNG/JPEG whose headers claim huge sizes,
  valid PNGs of 16 Mpixels that compress to ~50 kB, thousands of tiny chunks, segments or
  fill bytes before the size, progressive JPEGs with thousands of scans.
- control: JSON structure edits (values replaced by huge strings, huge or non-finite
  numbers, wrong types, deep nesting), byte-level edits of the JSON text, oversize messages.

Memory: each worker samples its resident set (/proc/self/statm) every ``RSS_EVERY`` cases;
the table gives it at start, after warm-up (the first chunk), at the end and its maximum.
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing
import os
import resource
import signal
import struct
import sys
import time
import traceback
import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import zstandard

sys.path.insert(0, str(Path(__file__).resolve().parent))  # shared_data, run as a script or not

from fleetslam.camera import Camera  # noqa: E402
from fleetslam.config import Config, WireConfig  # noqa: E402
from fleetslam.datasets.tum import RgbdSequence  # noqa: E402
from fleetslam.backend.robot_slam import RobotSlam  # noqa: E402
from fleetslam.pipeline.split import run_stages  # noqa: E402
from fleetslam.pipeline.states import CapturedFrame  # noqa: E402
from fleetslam.tables import format_table  # noqa: E402
from fleetslam.transport import protocol  # noqa: E402
from fleetslam.transport.protocol import Hello  # noqa: E402
from fleetslam.wire import binary  # noqa: E402
from fleetslam.wire.envelope import (  # noqa: E402
    FLAG_ZSTD,
    MAX_PAYLOAD_BYTES,
    Header,
    Kind,
    WireError,
    _assemble,
    open_message,
    seal,
)
from fleetslam.wire.frames import decode_frame_message, encode_frame_message  # noqa: E402
from fleetslam.wire.inter import Reference, reference_of  # noqa: E402
from fleetslam.wire.messages import (  # noqa: E402
    Feedback,
    KeyframeUpload,
    decode_feedback,
    decode_keyframe,
    encode_feedback,
    encode_keyframe,
)
from shared_data import SEVEN_SCENES  # noqa: E402

FAMILIES = ("payload", "header", "raw", "zstd_bomb", "image_bomb", "control")
# Share of the cases per family: payload edits reach deepest, so they get the most.
WEIGHTS = (0.40, 0.14, 0.10, 0.04, 0.10, 0.22)
ROBOT = "fuzz_robot"
CHUNK = 200  # cases per task handed to a worker
RSS_EVERY = 50  # cases between resident-set samples
CASE_TIMEOUT_S = 30.0  # a case still running then is a hang (reported, not waited for)
PAGE = os.sysconf("SC_PAGE_SIZE")


# ---------------------------------------------------------------------------------------
# Seeds: real messages and where their fields are
# ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Field:
    """A fixed-size field the decoder read: its offset in the payload and struct format."""

    offset: int
    fmt: str
    what: str


@dataclass
class Seed:
    name: str
    channel: str  # the key it arrives on: "frame", "keyframe" or "feedback"
    data: bytes  # the sealed message
    header: Header
    payload: bytes  # raw (decompressed) payload
    fields: list[Field] = field(default_factory=list)
    images: list[tuple[int, int]] = field(default_factory=list)  # payload spans of images


@dataclass
class Context:
    camera: Camera
    seeds: list[Seed]
    controls: list[tuple[str, bytes]]
    bombs: list[tuple[str, bytes, int]]  # (what, zstd frame, bytes it expands to)
    png_bombs: list[tuple[str, bytes, int, int, int, int]]  # (what, png, h, w, ch, itemsize)
    jpeg: bytes  # a small baseline JPEG, tables to patch
    progressive: bytes  # the same image as a progressive JPEG
    # The cloud's ring of reference frames (seq -> Reference) the inter-coded seeds use.
    references: dict[int, Reference] = field(default_factory=dict)

    def by_channel(self, channel: str) -> list[Seed]:
        return [s for s in self.seeds if s.channel == channel]


def decoder(channel: str, camera: Camera,
            references: dict[int, Reference] | None = None) -> Callable[[bytes], Any]:
    """What the cloud runs on bytes from a channel (feedback: what a robot runs); inter-coded
    frames find their references in ``references`` (the cloud's ring)."""
    if channel == "frame":
        return lambda data: decode_frame_message(data, camera, references or {})
    if channel == "keyframe":
        return lambda data: decode_keyframe(data, camera)
    return decode_feedback


def trace_fields(seed: Seed, camera: Camera,
                 references: dict[int, Reference] | None = None) -> None:
    """Decode the seed once with Reader.unpack recording every fixed field it reads: the
    field-aware mutations then edit exactly what the decoder interprets."""
    fields: list[Field] = []
    original = binary.Reader.unpack

    def recording(self: binary.Reader, fmt: str, what: str) -> tuple:
        fields.append(Field(self._pos, fmt, what))
        return original(self, fmt, what)

    binary.Reader.unpack = recording  # type: ignore[method-assign]
    try:
        decoder(seed.channel, camera, references)(seed.data)
    finally:
        binary.Reader.unpack = original  # type: ignore[method-assign]
    seed.fields = fields
    for f in fields:
        if f.fmt == "BHHBB":  # get_image: the image header, then its blob's length and bytes
            (n,) = struct.unpack_from("<I", seed.payload, f.offset + 7)
            seed.images.append((f.offset, f.offset + 11 + n))


def build_context(n_frames: int = 3, small: bool = False) -> Context:
    """Seeds from the 7-Scenes sequence (deterministic: same frames, same bytes). ``small``:
    1 MB zstd bombs and camera-sized PNG bombs only (the smoke test: built in a second)."""
    seq = RgbdSequence(SEVEN_SCENES, last=n_frames - 1)
    camera = seq.camera
    config = Config()
    frames = [CapturedFrame(f.index, f.timestamp, f.rgb, f.depth_m) for f in seq]
    messages: list[tuple[str, str, bytes]] = []
    references: dict[int, Reference] = {}
    variants = {"png+zstd": config.wire, "jpeg": WireConfig(frame_image_codec="jpeg"),
                "raw": WireConfig(compress=False)}
    for k in range(7):
        pipeline = RobotSlam.new(config, camera)
        robot, _ = pipeline.split(k)
        for seq_no, frame in enumerate(frames):
            state = run_stages(robot, frame, pipeline.sides)
            for vname, wire in variants.items():
                if vname == "jpeg" and k > 1 or vname == "raw" and seq_no != len(frames) - 1:
                    continue  # JPEG only changes images (k <= 1); one uncompressed frame
                data = encode_frame_message(state, k, ROBOT, seq_no, camera, wire)
                messages.append((f"frame k={k} #{frame.index} {vname}", "frame", data))
            # Inter-coded (wire/inter.py): as frame 100 + seq_no, against this very frame
            # (all descriptors coded) and, after the first, the frame before it too.
            ref = reference_of(state)
            if ref is None:
                continue
            references[seq_no] = ref
            refs = [(s, references[s]) for s in range(seq_no, max(-1, seq_no - 2), -1)]
            data = encode_frame_message(state, k, ROBOT, 100 + seq_no, camera, config.wire, refs)
            messages.append((f"frame k={k} #{frame.index} inter x{len(refs)}", "frame", data))
    for codec in ("jpeg", "png"):
        f = frames[-1]
        raw = camera.metres_to_depth(f.depth_m)
        for stride in (config.map.pixel_stride, 1):
            kf = KeyframeUpload.from_frame(f.index, f.timestamp, f.rgb, raw, stride)
            data = encode_keyframe(ROBOT, 3, kf, WireConfig(keyframe_rgb_codec=codec))
            messages.append((f"keyframe {codec} stride {stride}", "keyframe", data))
    T = np.eye(4)
    T[:3, 3] = (0.1, -0.2, 1.5)
    for tracked in (True, False):
        fb = Feedback(7, frames[0].timestamp, tracked, tracked, 250, T, 12.5)
        messages.append((f"feedback tracked={tracked}", "feedback", encode_feedback(ROBOT, 7, fb)))
    seeds = []
    for name, channel, data in messages:
        header, payload = open_message(data)
        seed = Seed(name, channel, data, header, payload)
        trace_fields(seed, camera, references)
        seeds.append(seed)
    return Context(camera, seeds, control_seeds(camera), zstd_bombs(seeds, small),
                   png_bombs(small), *small_jpegs(), references)


def control_seeds(camera: Camera) -> list[tuple[str, bytes]]:
    """Every control message the builders make (the cloud parses all of them: a robot or a
    client may send any)."""
    poses = {3: np.eye(4), 17: np.eye(4)}
    messages = [
        Hello(0, camera, "7scenes", False).message(600),
        Hello(2, camera, "robot.tum", True).message(10),
        Hello(6, Camera(517.3, 516.5, 318.6, 255.3, distortion=(0.26, -0.95, -0.005, 0.003, 1.16)),
              "", False).message(0),
        *(m.message() for m in (
            protocol.End(599, poses), protocol.End(10), protocol.Ending(),
            protocol.Need((3, 17)), protocol.Ended({"frames": 600, "ate_m": 0.05}),
            protocol.Ack(17), protocol.Welcome(True, 18, 20, 2, 8),
            protocol.Error.of(protocol.Code.REJECTED, "frame rejected: x", rejected="frame"),
            protocol.Error.of(protocol.Code.REFERENCE_MISSING, "frame rejected: y",
                              rejected="frame", seq=12, missing=(9, 10)))),
        *(m.message() for m in (
            protocol.Request("status", "a" * 32), protocol.Request("merge", "b" * 32),
            protocol.StatusReply("c" * 32, {"r1": {"frames": 3, "finished": False}},
                                 {"state": "idle"}),
            protocol.Merged("d" * 32, {"robots": 2}))),
    ]
    return [(m["type"], protocol.encode(m)) for m in messages]


def zstd_bombs(seeds: list[Seed], small: bool = False) -> list[tuple[str, bytes, int]]:
    """zstd frames that expand far beyond their size: zeros, and real payloads whose first
    count or length field claims the most, padded with zeros so the claim seems backed."""
    cctx = zstandard.ZstdCompressor(level=1, write_content_size=True)
    bombs = []
    sizes = (1 << 20,) if small else (1 << 20, 16 << 20, MAX_PAYLOAD_BYTES,
                                      MAX_PAYLOAD_BYTES + 1, 4 * MAX_PAYLOAD_BYTES)
    for size in sizes:
        bombs.append((f"zeros {size}", cctx.compress(bytes(size)), size))
    for seed in seeds:
        if seed.channel == "feedback":
            continue
        for f in seed.fields:
            if f.fmt not in ("I", "HH"):
                continue
            big = struct.pack("<" + f.fmt, *([0xFFFFFFFF] if f.fmt == "I" else [0xFFFF, 0xFFFF]))
            head = seed.payload[:f.offset] + big
            for total in (1 << 20,) if small else (16 << 20, MAX_PAYLOAD_BYTES):
                body = head + bytes(total - len(head))
                bombs.append((f"{seed.name}: {f.what} max, {total} B", cctx.compress(body), total))
            if f.what == "keypoint count" and not small:  # the most the reader once read
                for mode in (0, 1):
                    body = seed.payload[:f.offset] + struct.pack("<IB", 1 << 20, mode)
                    body += bytes(MAX_PAYLOAD_BYTES - len(body))
                    bombs.append((f"{seed.name}: 2^20 keypoints mode {mode}",
                                  cctx.compress(body), len(body)))
            break  # the first count of each seed: the decoder gets furthest with it
    return bombs


def _png(h: int, w: int, bit_depth: int, colour: int, idat: list[bytes],
         extra: list[tuple[bytes, bytes]] = (), crc_ok: bool = True) -> bytes:
    def chunk(kind: bytes, body: bytes) -> bytes:
        crc = zlib.crc32(kind + body) if crc_ok else 0
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", crc)

    out = [b"\x89PNG\r\n\x1a\n", chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, bit_depth, colour,
                                                            0, 0, 0))]
    out += [chunk(k, b) for k, b in extra]
    out += [chunk(b"IDAT", d) for d in idat]
    out.append(chunk(b"IEND", b""))
    return b"".join(out)


def png_bombs(small: bool = False) -> list[tuple[str, bytes, int, int, int, int]]:
    """Valid PNGs of up to MAX_IMAGE_PIXELS that compress to ~50 kB (zlib stops at ~1000:1)."""
    out = []
    sizes = ((480, 640),) if small else ((4096, 4096), (256, 65535), (65535, 256), (480, 640))
    for h, w in sizes:
        for bit_depth, colour, ch, itemsize in ((8, 2, 3, 1), (16, 0, 1, 2), (8, 0, 1, 1)):
            row = w * ch * itemsize
            stream = zlib.compress(bytes((row + 1) * h), 9)  # filter byte 0 + zero pixels
            out.append((f"png {w}x{h} {ch}x{8 * itemsize} bit", _png(h, w, bit_depth, colour,
                                                                     [stream]), h, w, ch,
                        itemsize))
    return out


def small_jpegs() -> tuple[bytes, bytes]:
    rng = np.random.default_rng(0)
    image = cv2.resize(rng.integers(0, 256, (8, 8, 3), dtype=np.uint8), (64, 48))
    ok1, base = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 80])
    ok2, prog = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 80,
                                             cv2.IMWRITE_JPEG_PROGRESSIVE, 1])
    assert ok1 and ok2
    return base.tobytes(), prog.tobytes()


# ---------------------------------------------------------------------------------------
# Mutations
# ---------------------------------------------------------------------------------------

Rng = np.random.Generator


def pick(rng: Rng, items: list | tuple) -> Any:
    return items[int(rng.integers(len(items)))]


def _int_edits(value: int, fmt: str) -> list[int]:
    bits = 8 * struct.calcsize("<" + fmt)
    signed = fmt.islower()
    lo, hi = (-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if signed else (0, (1 << bits) - 1)
    cands = [0, 1, hi, hi - 1, lo, value + 1, value - 1, value * 2, value // 2,
             (1 << (bits - 1)) - 1, 1 << (bits - 1), -1, 0x7FFF, 0x10000, 1 << 20, (1 << 20) + 1,
             20_001, 480, 640, 4096, 65535]
    return [c for c in cands if lo <= c <= hi]


_FLOAT_EDITS = (0.0, -0.0, 1.0, -1.0, math.nan, math.inf, -math.inf, 1e38, -1e38, 1e-45,
                3.4028235e38, 1e308, 5e-324)


def edit_field(payload: bytearray, f: Field, rng: Rng) -> None:
    """Set one item of a traced field to a boundary value of its type."""
    fmt = "<" + f.fmt
    if f.offset + struct.calcsize(fmt) > len(payload):
        return
    values = list(struct.unpack_from(fmt, payload, f.offset))
    i = int(rng.integers(len(values)))
    code = f.fmt[i]
    if code in "fd":
        values[i] = pick(rng, _FLOAT_EDITS) if rng.random() < 0.8 else float(rng.normal() * 1e3)
    else:
        values[i] = pick(rng, _int_edits(int(values[i]), code))
    try:
        struct.pack_into(fmt, payload, f.offset, *values)
    except (struct.error, OverflowError):  # a float edit too large for f4: leave it
        pass


def mutate_bytes(data: bytearray, rng: Rng, fields: list[Field] = (),
                 donors: list[bytes] = ()) -> bytearray:
    """One to four stacked edits; field-aware edits half the time when fields are known."""
    for _ in range(int(rng.integers(1, 5))):
        n = len(data)
        op = int(rng.integers(9))
        if fields and rng.random() < 0.5:
            edit_field(data, pick(rng, fields), rng)
        elif op == 0 and n:  # bit flips
            for pos in rng.integers(0, n, int(rng.integers(1, 9))):
                data[pos] ^= 1 << int(rng.integers(8))
        elif op == 1 and n:  # byte sets
            for pos in rng.integers(0, n, int(rng.integers(1, 9))):
                data[pos] = pick(rng, (0, 0xFF, 0x7F, 0x80, int(rng.integers(256))))
        elif op == 2:  # truncation
            del data[int(rng.integers(n + 1)):]
        elif op == 3:  # insertion
            pos = int(rng.integers(n + 1))
            data[pos:pos] = rng.integers(0, 256, int(rng.integers(1, 65)), dtype=np.uint8).tobytes()
        elif op == 4 and n:  # deletion
            a = int(rng.integers(n))
            del data[a:a + int(rng.integers(1, 65))]
        elif op == 5 and n:  # duplicated range
            a = int(rng.integers(n))
            b = min(n, a + int(rng.integers(1, 4097)))
            c = int(rng.integers(n + 1))
            data[c:c] = data[a:b]
        elif op == 6 and donors:  # splice with another payload of the same channel
            donor = pick(rng, donors)
            data[int(rng.integers(n + 1)):] = donor[int(rng.integers(len(donor) + 1)):]
        elif op == 7 and n >= 4:  # a 4-byte little-endian integer anywhere set to a boundary
            pos = int(rng.integers(n - 3))
            data[pos:pos + 4] = struct.pack("<I", pick(rng, (0, 0xFFFFFFFF, 0x7FFFFFFF,
                                                                0x80000000, 1 << 20)))
        elif op == 8 and n:  # a run of zeros or 0xFF
            a = int(rng.integers(n))
            data[a:a + int(rng.integers(1, 257))] = bytes([pick(rng, (0, 0xFF))]) * 256
    return data


def reseal(seed: Seed, payload: bytes, rng: Rng, kind: Kind | None = None,
           split_point: int | None = None) -> bytes:
    """The envelope's own seal: a valid CRC, so the payload decoder sees the bytes."""
    return seal(seed.header.kind if kind is None else kind, seed.header.robot_id, seed.header.seq,
                seed.header.timestamp,
                seed.header.split_point if split_point is None else split_point,
                payload, compress=rng.random() < 0.3, level=1)


def case_payload(ctx: Context, rng: Rng) -> tuple[str, bytes]:
    seed = pick(rng, ctx.seeds)
    donors = [s.payload for s in ctx.by_channel(seed.channel)]
    payload = mutate_bytes(bytearray(seed.payload), rng, seed.fields, donors)
    return seed.channel, reseal(seed, bytes(payload), rng)


# Header offsets (envelope.py): magic 0, version 4, kind 6, split 7, flags 8, id length 9,
# robot id 10; then from 10 + L: seq, timestamp, raw length, payload length, CRC.
_TAIL = struct.Struct("<QdII")


def _split_header(data: bytes) -> tuple[dict[str, Any], bytes]:
    magic, version, kind, split, flags, id_len = struct.unpack_from("<4sHBBBB", data)
    seq, ts, raw_len, pay_len = _TAIL.unpack_from(data, 10 + id_len)
    fields = dict(magic=magic, version=version, kind=kind, split=split, flags=flags,
                  robot_id=data[10:10 + id_len], id_len=id_len, seq=seq, ts=ts, raw_len=raw_len,
                  pay_len=pay_len, crc=struct.unpack_from("<I", data, 34 + id_len)[0])
    return fields, data[38 + id_len:]


def _join_header(h: dict[str, Any], payload: bytes, crc_ok: bool) -> bytes:
    head = (struct.pack("<4sHBBBB", h["magic"], h["version"], h["kind"], h["split"], h["flags"],
                        h["id_len"]) + h["robot_id"]
            + _TAIL.pack(h["seq"], h["ts"], h["raw_len"], h["pay_len"]))
    crc = zlib.crc32(payload, zlib.crc32(head)) if crc_ok else h["crc"]
    return head + struct.pack("<I", crc) + payload


def case_header(ctx: Context, rng: Rng) -> tuple[str, bytes]:
    seed = pick(rng, ctx.seeds)
    h, payload = _split_header(seed.data)
    for _ in range(int(rng.integers(1, 4))):
        name = pick(rng, ("version", "kind", "split", "flags", "id_len", "robot_id", "seq", "ts",
                          "raw_len", "pay_len", "crc", "magic"))
        if name == "version":
            h[name] = pick(rng, (0, 2, 0xFFFF, int(rng.integers(0x10000))))
        elif name == "kind":
            h[name] = pick(rng, (0, 1, 2, 3, 4, 0xFF))
        elif name == "split":  # 0..6 hands the payload to another split point's decoder
            h[name] = pick(rng, (0, 1, 2, 3, 4, 5, 6, 7, 0xFF))
        elif name == "flags":
            h[name] = pick(rng, (0, FLAG_ZSTD, 0x02, 0x80, 0xFF, h["flags"] ^ FLAG_ZSTD))
        elif name == "id_len":
            h[name] = pick(rng, (0, 1, 64, 65, 0xFF, max(0, h["id_len"] - 1), h["id_len"] + 1))
        elif name == "robot_id":
            h[name] = pick(rng, (b"a b", b"\xff\xfe", b"r/1", b"x" * 64, "é".encode(),
                                 b"\x00" * len(h["robot_id"])))
            h["id_len"] = len(h["robot_id"]) if rng.random() < 0.8 else h["id_len"]
        elif name == "seq":
            h[name] = pick(rng, (0, (1 << 64) - 1, 1 << 63))
        elif name == "ts":
            h[name] = pick(rng, (math.nan, math.inf, -math.inf, -0.0, 0.0, 1e308, h["ts"] + 1e-6))
        elif name in ("raw_len", "pay_len"):
            h[name] = pick(rng, (0, 1, h[name] - 1, h[name] + 1, MAX_PAYLOAD_BYTES,
                                 MAX_PAYLOAD_BYTES + 1, 0xFFFFFFFF, len(payload)))
            h[name] = max(0, min(0xFFFFFFFF, h[name]))
        elif name == "crc":
            h[name] = int(rng.integers(1 << 32))
        else:
            h[name] = pick(rng, (b"FSLN", b"\0\0\0\0", b"MLSF"))
    h["id_len"] = min(h["id_len"], 0xFF)
    data = _join_header(h, payload, crc_ok=rng.random() < 0.7)
    if h["id_len"] != len(h["robot_id"]) and rng.random() < 0.5:
        data = data[:len(data) - int(rng.integers(0, 8))]
    return seed.channel, data


def case_raw(ctx: Context, rng: Rng) -> tuple[str, bytes]:
    channel = pick(rng, ("frame", "frame", "keyframe", "feedback"))
    seeds = ctx.by_channel(channel)
    op = int(rng.integers(6))
    n = int(np.exp(rng.uniform(0, np.log(65536))))
    noise = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
    if op == 0:
        return channel, noise[:int(rng.integers(0, 64))] if rng.random() < 0.3 else noise
    if op == 1:
        return channel, b"FSLM" + struct.pack("<H", 1) + noise
    seed = pick(rng, seeds)
    if op == 2:
        return channel, seed.data[:int(rng.integers(len(seed.data) + 1))]
    if op == 3:
        return channel, seed.data + noise[:int(rng.integers(1, 65))]
    if op == 4:  # the real header, random payload: the CRC catches it
        h, _ = _split_header(seed.data)
        h["pay_len"] = h["raw_len"] = n
        return channel, _join_header(h, noise, crc_ok=False)
    # A random payload in a valid envelope: every split point's decoder on noise.
    flags = 0
    if rng.random() < 0.3:
        noise, flags = zstandard.ZstdCompressor(level=1).compress(noise), FLAG_ZSTD
    kind = {"frame": 1, "keyframe": 3, "feedback": 2}[channel]
    return channel, _assemble(1, kind, int(rng.integers(7)), flags, ROBOT.encode(), 0,
                              seed.header.timestamp, n, noise)


def case_zstd_bomb(ctx: Context, rng: Rng) -> tuple[str, bytes]:
    what, frame, size = pick(rng, ctx.bombs)
    channel = "keyframe" if what.startswith("keyframe") else "frame"
    channel = channel if rng.random() < 0.8 else pick(rng, ("frame", "keyframe", "feedback"))
    declared = pick(rng, (size, size, size, size - 1, size + 1, 0, 100, MAX_PAYLOAD_BYTES,
                          MAX_PAYLOAD_BYTES + 1, 0xFFFFFFFF))
    declared = max(0, min(declared, 0xFFFFFFFF))
    op = int(rng.integers(6))
    if op == 1:  # corrupt the compressed body past its frame header
        b = bytearray(frame)
        for pos in rng.integers(min(len(b) - 1, 18), len(b), int(rng.integers(1, 5))):
            b[pos] ^= 1 << int(rng.integers(8))
        frame = bytes(b)
    elif op == 2:  # two frames back to back, or trailing garbage
        frame = frame + pick(rng, (frame, b"\0" * 8, b"\x28\xb5\x2f\xfd"))
    elif op == 3:  # the frame header's content size field rewritten
        b = bytearray(frame)
        for pos in range(5, min(len(b), 13)):
            if rng.random() < 0.5:
                b[pos] = int(rng.integers(256))
        frame = bytes(b)
    elif op == 4:  # truncated
        frame = frame[:int(rng.integers(len(frame)))]
    flags = FLAG_ZSTD if rng.random() < 0.95 else 0
    kind = {"frame": 1, "keyframe": 3, "feedback": 2}[channel]
    split = pick(rng, [s.header.split_point for s in ctx.seeds if s.name in what] or [0])
    seed = next((s for s in ctx.seeds if what.startswith(s.name)), ctx.seeds[0])
    return channel, _assemble(1, kind, split, flags, ROBOT.encode(), 0, seed.header.timestamp,
                              declared, frame)


# JPEG markers.
_SOI, _EOI = b"\xff\xd8", b"\xff\xd9"


def _jpeg_segments(data: bytes) -> list[tuple[int, int, int]]:
    """(marker, start, end) of each marker segment up to the first SOS."""
    out, i = [], 2
    while i + 4 <= len(data) and data[i] == 0xFF:
        marker = data[i + 1]
        (length,) = struct.unpack(">H", data[i + 2:i + 4])
        out.append((marker, i, i + 2 + length))
        if marker == 0xDA:
            break
        i += 2 + length
    return out


def _jpeg_with_size(jpeg: bytes, h: int, w: int) -> bytes:
    b = bytearray(jpeg)
    for marker, start, _ in _jpeg_segments(jpeg):
        if marker in (0xC0, 0xC2):
            b[start + 5:start + 9] = struct.pack(">HH", h, w)
    return bytes(b)


def crafted_image(ctx: Context, rng: Rng) -> tuple[bytes, int, int, int, int, int]:
    """(image bytes, codec id, h, w, channels, itemsize) of a hostile image."""
    sizes = ((4096, 4096), (65535, 256), (256, 65535), (480, 640), (240, 320), (1, 1),
             (65535, 65535), (0, 0), (4097, 4096))
    h, w = pick(rng, sizes)
    op = int(rng.integers(9))
    if op == 0:  # a valid PNG bomb, ~50 kB for 16 Mpixels
        _, png, h, w, ch, itemsize = pick(rng, ctx.png_bombs)
        return png, 0, h, w, ch, itemsize
    ch, itemsize = pick(rng, ((3, 1), (1, 2), (1, 1)))
    bit_depth, colour = (16, 0) if itemsize == 2 else (8, 2 if ch == 3 else 0)
    if op == 1:  # header only, truncated or garbage IDAT
        idat = pick(rng, ([], [b""], [zlib.compress(bytes(1000))],
                          [rng.integers(0, 256, 100, dtype=np.uint8).tobytes()]))
        return _png(h, w, bit_depth, colour, idat, crc_ok=rng.random() < 0.8), 0, h, w, ch, \
            itemsize
    if op == 2:  # many tiny IDAT chunks, or many ancillary chunks first
        stream = zlib.compress(bytes(min((w * ch * itemsize + 1) * h, 1 << 22)), 9)
        count = int(np.exp(rng.uniform(0, np.log(1 << 20))))
        if rng.random() < 0.5:
            idat = [stream[i:i + 1] for i in range(len(stream))] + [b""] * count
            extra: list[tuple[bytes, bytes]] = []
        else:
            idat, extra = [stream], [(pick(rng, (b"tEXt", b"zzzz", b"iTXt")), b"k\0v")] * count
        return _png(h, w, bit_depth, colour, idat, extra), 0, h, w, ch, itemsize
    ch, itemsize = pick(rng, ((3, 1), (1, 1)))
    if op == 3:  # a real JPEG's tables with a huge size and little data
        return _jpeg_with_size(pick(rng, (ctx.jpeg, ctx.progressive)), h, w), 1, h, w, ch, 1
    if op == 4:  # many tiny segments (or fill bytes) before the size
        count = int(np.exp(rng.uniform(0, np.log(8 << 20))))
        filler = pick(rng, (b"\xff\xfe\x00\x02", b"\xff\xe1\x00\x02", b"\xff"))
        sof = [s for s in _jpeg_segments(ctx.jpeg) if s[0] == 0xC0][0]
        body = _jpeg_with_size(ctx.jpeg, h, w)
        return body[:sof[1]] + filler * count + body[sof[1]:], 1, h, w, ch, 1
    if op == 5:  # a progressive JPEG with its scans repeated: each pass visits every block
        prog = _jpeg_with_size(ctx.progressive, h, w)
        segs = _jpeg_segments(prog)
        first_sos = segs[-1][1]
        scans = prog[first_sos:prog.rindex(_EOI)]
        count = int(np.exp(rng.uniform(0, np.log(5000))))
        return prog[:first_sos] + scans * count + _EOI, 1, h, w, ch, 1
    if op == 6:  # SOF then a flood of RST markers or empty SOS segments
        body = _jpeg_with_size(ctx.jpeg, h, w)
        cut = body.rindex(_EOI)
        count = int(np.exp(rng.uniform(0, np.log(1 << 20))))
        flood = pick(rng, (b"\xff\xd0", b"\xff\xda\x00\x08\x01\x01\x00\x00\x3f\x00"))
        return body[:cut] + flood * count + _EOI, 1, h, w, ch, 1
    if op == 7:  # the real image, its size fields lying in the wire header
        data = pick(rng, (ctx.jpeg, ctx.progressive))
        return data, 1, pick(rng, (48, 47, 0, 65535)), pick(rng, (64, 63, 0, 65535)), ch, 1
    data = bytearray(_jpeg_with_size(ctx.jpeg, h, w))  # bit flips in a small JPEG
    for pos in rng.integers(2, len(data), int(rng.integers(1, 9))):
        data[pos] ^= 1 << int(rng.integers(8))
    return bytes(data), 1, h, w, ch, 1


def case_image_bomb(ctx: Context, rng: Rng) -> tuple[str, bytes]:
    seed = pick(rng, [s for s in ctx.seeds if s.images])
    start, end = pick(rng, seed.images)
    image, codec, h, w, ch, itemsize = crafted_image(ctx, rng)
    if rng.random() < 0.1:  # the wire header disagrees with the image's
        h, w = pick(rng, ((h + 1, w), (h, w - 1), (w, h)))
    h, w = (max(0, min(v, 0xFFFF)) for v in (h, w))
    head = struct.pack("<BHHBBI", codec, h, w, ch, itemsize, len(image))
    payload = seed.payload[:start] + head + image + seed.payload[end:]
    return seed.channel, seal(seed.header.kind, ROBOT, 1, seed.header.timestamp,
                              seed.header.split_point, payload, compress=True, level=1)


_KNOWN_TYPES = ("hello", "end", "status", "merge", "ack", "need", "welcome", "ended", "error",
                "ending", "merged", "", "HELLO", "x" * 1000)


def _evil_value(rng: Rng) -> Any:
    op = int(rng.integers(16))
    if op == 0:
        return None
    if op == 1:
        return pick(rng, (True, False))
    if op == 2:
        return pick(rng, (0, -1, 1, 2**31, 2**63, 2**64, 10**400, -(10**400)))
    if op == 3:
        return pick(rng, (math.nan, math.inf, -math.inf, 1e308, -0.0, 1e-320, 0.5))
    if op == 4:
        return "x" * int(np.exp(rng.uniform(0, np.log(2 << 20))))
    if op == 5:
        return pick(rng, ("", "é", "\ud800", "\x00", "null", "1e400"))
    if op == 6:
        return []
    if op == 7:
        return {}
    if op == 8:  # deep nesting
        v: Any = 1
        for _ in range(int(np.exp(rng.uniform(0, np.log(3000))))):
            v = [v] if rng.random() < 0.5 else {"a": v}
        return v
    if op == 9:
        return list(range(int(np.exp(rng.uniform(0, np.log(200_000))))))
    if op == 10:
        return [[math.nan] * 4] * 4
    if op == 11:
        return {str(i): np.eye(4).tolist() for i in range(int(rng.integers(1, 50)))}
    if op == 12:
        return [pick(rng, (1.0, "a", None, [], {}))] * int(rng.integers(0, 10))
    if op == 13:
        return {pick(rng, ("-1", "1e5", "x", "", "9" * 5000)): pick(rng, (np.eye(4).tolist(),
                                                                         "a", [1] * 16, None))}
    if op == 14:
        return [list(range(4))] * 4
    return pick(rng, _KNOWN_TYPES)


def _paths(node: Any, prefix: tuple = ()) -> Iterator[tuple]:
    yield prefix
    if len(prefix) >= 6:  # an earlier edit may have nested it thousands deep
        return
    if isinstance(node, dict):
        for k, v in node.items():
            yield from _paths(v, prefix + (k,))
    elif isinstance(node, list):
        for i, v in enumerate(node[:8]):
            yield from _paths(v, prefix + (i,))


def _replace(node: Any, path: tuple, value: Any, delete: bool = False) -> Any:
    if not path:
        return value
    parent = node
    for key in path[:-1]:
        parent = parent[key]
    if delete:
        del parent[path[-1]]
    else:
        parent[path[-1]] = value
    return node


def case_control(ctx: Context, rng: Rng) -> tuple[str, bytes]:
    _, text = pick(rng, ctx.controls)
    if rng.random() < 0.25:  # byte level
        return "control", bytes(mutate_bytes(bytearray(text), rng))
    message = json.loads(text)
    for _ in range(int(rng.integers(1, 4))):
        paths = list(_paths(message))
        path = pick(rng, paths)
        op = int(rng.integers(6))
        if op == 0 and path:
            message = _replace(message, path, None, delete=True)
        elif op == 1 and isinstance(message, dict):
            message["type"] = pick(rng, _KNOWN_TYPES)
        elif op == 2 and isinstance(message, dict):
            message[pick(rng, ("junk", "camera", "keyframe_poses", "id", "protocol", "offload_at",
                               "adaptive", "source", "last_seq"))] = _evil_value(rng)
        elif op == 3 and rng.random() < 0.2:
            message = pick(rng, ([message], "hello", 1, None, [], {}))
        else:
            message = _replace(message, path, _evil_value(rng))
    try:
        data = json.dumps(message).encode()
    except (RecursionError, ValueError):  # the generator's own limits: send it anyway
        data = b"[" * 100_000
    except UnicodeEncodeError:
        data = text
    if rng.random() < 0.05:
        data = pick(rng, (data.decode("utf-8", "replace").encode("utf-16"), b"\xef\xbb\xbf" + data,
                          data + b" " * (protocol.MAX_CONTROL_BYTES + 1 - len(data))))
    return "control", data


GENERATORS: dict[str, Callable[[Context, Rng], tuple[str, bytes]]] = {
    "payload": case_payload, "header": case_header, "raw": case_raw,
    "zstd_bomb": case_zstd_bomb, "image_bomb": case_image_bomb, "control": case_control}


# ---------------------------------------------------------------------------------------
# Running cases
# ---------------------------------------------------------------------------------------


def handle_control(data: bytes) -> None:
    """What the cloud does with a control message before acting on it (routing.py and
    robot_session.py): parse; a hello's fields, an end's, a request's id; and what a robot
    does with a reply (protocol.parse_reply)."""
    message = protocol.parse_control(data)
    if message["type"] == "hello":
        Hello.parse(message)
    elif message["type"] == "end":
        protocol.End.parse(message)
    elif message["type"] in protocol.REPLIES:
        protocol.parse_reply(data)
    elif message["type"] in protocol.OPERATOR_REPLIES:
        protocol.parse_operator_reply(data)
    protocol.request_id(message)


def make_case(ctx: Context, family: str, seed: int, index: int) -> tuple[str, bytes]:
    rng = np.random.default_rng([seed, FAMILIES.index(family), index])
    return GENERATORS[family](ctx, rng)


class CaseTimeout(Exception):
    pass


def _alarm(signum: int, frame: Any) -> None:
    raise CaseTimeout(f"still running after {CASE_TIMEOUT_S} s")


def run_case(ctx: Context, family: str, seed: int, index: int) -> tuple[float, dict | None]:
    """(decode seconds, the finding or None). Clean: WireError for binary messages,
    ValueError for control messages."""
    channel, data = make_case(ctx, family, seed, index)
    clean = ValueError if channel == "control" else WireError
    run = handle_control if channel == "control" else decoder(channel, ctx.camera, ctx.references)
    start = time.perf_counter()
    try:
        run(data)
        error = None
    except clean:
        error = None
    except Exception as exc:  # noqa: BLE001 - the finding
        error = {"family": family, "seed": seed, "index": index, "channel": channel,
                 "bytes": len(data), "type": type(exc).__name__, "message": str(exc)[:300],
                 "where": traceback.format_exc().strip().splitlines()[-3].strip()}
    return time.perf_counter() - start, error


def rss_bytes() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * PAGE


_CTX: Context | None = None  # built before the workers fork


def _quiet() -> None:
    """libpng and libjpeg print a line per broken image on stderr: a worker's go nowhere
    (findings come back as data)."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 2)
    os.close(devnull)


def run_chunk(task: tuple[int, list[tuple[str, int]]]) -> dict:
    seed, cases = task
    assert _CTX is not None
    previous = signal.signal(signal.SIGALRM, _alarm)
    times = np.zeros(len(cases))
    findings, rss = [], []
    for i, (family, index) in enumerate(cases):
        signal.setitimer(signal.ITIMER_REAL, CASE_TIMEOUT_S)
        try:
            times[i], error = run_case(_CTX, family, seed, index)
        except CaseTimeout as exc:  # raised in generation: still a hang of the run
            times[i], error = CASE_TIMEOUT_S, {"family": family, "seed": seed, "index": index,
                                               "type": "CaseTimeout", "message": str(exc)}
        finally:
            signal.setitimer(signal.ITIMER_REAL, 0)
        if error is not None:
            findings.append(error)
        if i % RSS_EVERY == 0:
            rss.append(rss_bytes())
    rss.append(rss_bytes())
    signal.signal(signal.SIGALRM, previous)
    return {"pid": os.getpid(), "families": [f for f, _ in cases], "indices":
            [x for _, x in cases], "times": times, "findings": findings,
            "rss": rss, "maxrss_kb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss}


def schedule(n_cases: int, seed: int) -> list[tuple[str, int]]:
    """The cases, families interleaved at random (so chunks cost alike); per family the
    indices are 0, 1, 2, ... whatever the total, so a reproducer stays valid."""
    counts = np.floor(np.array(WEIGHTS) * n_cases).astype(int)
    counts[0] += n_cases - counts.sum()
    cases = [(fam, i) for fam, c in zip(FAMILIES, counts) for i in range(c)]
    order = np.random.default_rng(seed).permutation(len(cases))
    return [cases[j] for j in order]


def fuzz(ctx: Context, n_cases: int, seed: int, workers: int, slow_s: float,
         progress: bool = True) -> dict:
    """Run the cases and summarise them (the JSON the bench writes)."""
    global _CTX
    _CTX = ctx
    cases = schedule(n_cases, seed)
    tasks = [(seed, cases[i:i + CHUNK]) for i in range(0, len(cases), CHUNK)]
    start = time.perf_counter()
    results = []
    if workers <= 1:
        iterator: Iterator[dict] = map(run_chunk, tasks)
        pool = None
    else:
        pool = multiprocessing.get_context("fork").Pool(workers, initializer=_quiet)
        iterator = pool.imap_unordered(run_chunk, tasks)
    try:
        for i, result in enumerate(iterator):
            results.append(result)
            if progress and (i + 1) % max(1, len(tasks) // 20) == 0:
                done = sum(len(r["times"]) for r in results)
                print(f"  {done}/{n_cases} cases, {time.perf_counter() - start:.0f} s, "
                      f"{sum(len(r['findings']) for r in results)} findings", flush=True)
    finally:
        if pool is not None:
            pool.close()
            pool.join()
    wall = time.perf_counter() - start
    return summarise(results, n_cases, seed, workers, wall, slow_s)


def summarise(results: list[dict], n_cases: int, seed: int, workers: int, wall: float,
              slow_s: float) -> dict:
    fams = np.concatenate([np.asarray(r["families"]) for r in results])
    idx = np.concatenate([np.asarray(r["indices"]) for r in results])
    times = np.concatenate([r["times"] for r in results])
    findings = [f for r in results for f in r["findings"]]
    per_family = {}
    for fam in FAMILIES:
        t = times[fams == fam]
        per_family[fam] = {
            "cases": int(len(t)),
            "unclean": sum(f["family"] == fam for f in findings),
            "max_ms": float(1000 * t.max()) if len(t) else 0.0,
            "p999_ms": float(1000 * np.percentile(t, 99.9)) if len(t) else 0.0,
            "mean_ms": float(1000 * t.mean()) if len(t) else 0.0,
            "slow": int((t > slow_s).sum())}
    slow_order = np.argsort(times)[::-1]
    slowest = [{"family": str(fams[j]), "seed": seed, "index": int(idx[j]),
                "ms": float(1000 * times[j])}
               for j in slow_order[:max(10, int((times > slow_s).sum()))]]
    # Memory per worker, in the order its chunks finished (a worker's chunks run in turn).
    memory = {}
    for r in results:
        memory.setdefault(r["pid"], []).append(r)
    rss = {}
    for pid, rs in memory.items():
        samples = [s for r in rs for s in r["rss"]]
        rss[str(pid)] = {"start_mb": samples[0] / 2**20,
                         "after_warmup_mb": rs[0]["rss"][-1] / 2**20,
                         "end_mb": samples[-1] / 2**20, "max_mb": max(samples) / 2**20,
                         "peak_maxrss_mb": max(r["maxrss_kb"] for r in rs) / 1024,
                         "samples": len(samples),
                         # ten evenly spaced samples: flat, or growing case after case?
                         "trace_mb": [samples[j] / 2**20 for j in
                                      np.linspace(0, len(samples) - 1, 10).astype(int)]}
    return {"cases": int(len(times)), "requested": n_cases, "seed": seed, "workers": workers,
            "wall_s": wall, "slow_threshold_s": slow_s,
            "unclean": len(findings), "slow": int((times > slow_s).sum()),
            "max_ms": float(1000 * times.max()), "p999_ms": float(1000 * np.percentile(times,
                                                                                     99.9)),
            "families": per_family, "findings": findings[:200],
            "slowest": slowest,  # every case over the threshold, at least the 10 slowest
            "rss": rss}


def print_summary(s: dict, ctx: Context) -> None:
    print(f"{s['cases']} cases on {len(ctx.seeds)} wire seeds, {len(ctx.controls)} control "
          f"seeds, {len(ctx.bombs)} zstd and {len(ctx.png_bombs)} PNG bombs; seed {s['seed']}, "
          f"{s['workers']} workers, {s['wall_s']:.0f} s")
    rows = [[fam, v["cases"], v["unclean"], v["slow"], v["mean_ms"], v["p999_ms"], v["max_ms"]]
            for fam, v in s["families"].items()]
    rows.append(["all", s["cases"], s["unclean"], s["slow"], None, s["p999_ms"], s["max_ms"]])
    print(format_table(["family", "cases", "unclean", f"> {s['slow_threshold_s']:g} s",
                        "mean ms", "p99.9 ms", "max ms"], rows))
    rows = [[pid, m["start_mb"], m["after_warmup_mb"], m["end_mb"], m["max_mb"],
             m["peak_maxrss_mb"]] for pid, m in s["rss"].items()]
    print(format_table(["worker", "RSS start MB", "after warm-up MB", "end MB", "max sampled MB",
                        "peak (ru_maxrss) MB"], rows))
    for f in s["findings"][:20]:
        print(f"UNCLEAN {f['type']}: {f['message'][:120]}  -- replay {f['family']}:{f['seed']}:"
              f"{f['index']}")
    for f in s["slowest"][:3]:
        print(f"slowest: {f['ms']:.1f} ms  -- replay {f['family']}:{f['seed']}:{f['index']}")


def replay(ctx: Context, spec: str) -> None:
    family, seed, index = spec.split(":")
    channel, data = make_case(ctx, family, int(seed), int(index))
    print(f"{family} case {index} (seed {seed}): {len(data)} bytes on the {channel} channel")
    run = handle_control if channel == "control" else decoder(channel, ctx.camera, ctx.references)
    start = time.perf_counter()
    try:
        run(data)
        print("accepted")
    except Exception:
        traceback.print_exc()
    print(f"{1000 * (time.perf_counter() - start):.1f} ms")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", type=int, default=100_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1))
    parser.add_argument("--slow-s", type=float, default=0.5)
    parser.add_argument("--replay", metavar="FAMILY:SEED:INDEX")
    parser.add_argument("--out", default=str(Path(__file__).parent / "results" /
                                             "fuzz_wire.json"))
    args = parser.parse_args()
    start = time.perf_counter()
    ctx = build_context()
    print(f"seeds built in {time.perf_counter() - start:.1f} s")
    if args.replay:
        return replay(ctx, args.replay)
    summary = fuzz(ctx, args.cases, args.seed, args.workers, args.slow_s)
    summary["seeds"] = [s.name for s in ctx.seeds] + [n for n, _ in ctx.controls]
    print_summary(summary, ctx)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(summary, indent=2))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()

"""What a ROS 2 node running rmw_zenoh puts on Zenoh, as rmw_zenoh's docs/design.md describes
it: the data key of a topic, the liveliness token of each publisher and subscription, the
attachment of each message, and the CDR payload. Pure functions, no session.

- Data key: ``<domain_id>/<topic without its leading slash>/<DDS type name>/<type hash>``,
  e.g. ``0/camera/rgb/image_color/sensor_msgs::msg::dds_::Image_/RIHS01_d31d...``. The hash is
  REP-2016's ``RIHS01_<sha256>`` on Iron and later, a placeholder (``TypeHashNotSupported``)
  on Humble; we subscribe with ``*`` in its place so every distribution matches.
- Liveliness: ``@ros2_lv/<domain_id>/<session_id>/<node_id>/<entity_id>/<kind>/<enclave>/
  <namespace>/<node>[/<topic>/<type>/<hash>/<qos>]``, names mangled ('/' -> '%'); kind MP
  is a publisher. ``@ros2_lv`` is a hermetic chunk: only a key starting with it matches.
- Attachment: int64 sequence number, int64 source time (ns since the epoch), both
  little-endian, then the publisher GID as one length byte (16) and its bytes.
- Payload: CDR with its 4-byte encapsulation header (0x00 0x00 big-endian, 0x00 0x01
  little-endian, then two option bytes); every camera message starts with std_msgs/Header.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

ADMIN_SPACE = "@ros2_lv"
PUBLISHER = "MP"
SUBSCRIPTION = "MS"
# Entity kinds of a topic or service endpoint; a node token (NN) has no topic.
ENDPOINT_KINDS = ("MP", "MS", "SS", "SC")
# Chunks of a token: the 9 of a node's, then topic, type, hash and QoS.
_NODE_CHUNKS = 9
_ENDPOINT_CHUNKS = 13
_ATTACHMENT = struct.Struct("<qqB")
_ENCAPSULATIONS = {b"\x00\x00": ">", b"\x00\x01": "<"}  # classic CDR, big / little endian
_STAMP = {"<": struct.Struct("<iI"), ">": struct.Struct(">iI")}
CDR_HEADER_SIZE = 4


def dds_type_name(ros_type: str) -> str:
    """``sensor_msgs/msg/Image`` -> ``sensor_msgs::msg::dds_::Image_`` (the key's type)."""
    package, kind, name = ros_type.split("/")
    return f"{package}::{kind}::dds_::{name}_"


def ros_type_name(dds_type: str) -> str | None:
    """``sensor_msgs::msg::dds_::Image_`` -> ``sensor_msgs/msg/Image``; None if it is not a
    ROS 2 type name in DDS form."""
    parts = dds_type.split("::")
    if len(parts) != 4 or parts[2] != "dds_" or not parts[3].endswith("_") or len(parts[3]) < 2:
        return None
    return f"{parts[0]}/{parts[1]}/{parts[3][:-1]}"


def normalise_topic(topic: str) -> str:
    """A fully qualified topic name: one leading slash, no trailing one."""
    return "/" + topic.strip("/")


def topic_key(domain_id: int, topic: str, type_name: str = "*", type_hash: str = "*") -> str:
    """The data key expression of ``topic``; by default any type and any hash."""
    return f"{domain_id}/{normalise_topic(topic)[1:]}/{type_name}/{type_hash}"


def key_topic(key: str) -> str:
    """The topic of a data key (the chunks between the domain and the type)."""
    return "/" + "/".join(key.split("/")[1:-2])


def key_type(key: str) -> str | None:
    """The ROS type of a data key (its second-to-last chunk), None if it names none."""
    chunks = key.split("/")
    return ros_type_name(chunks[-2]) if len(chunks) >= 4 else None


def liveliness_key(domain_id: int) -> str:
    """Every liveliness token of a domain."""
    return f"{ADMIN_SPACE}/{domain_id}/**"


def _demangle(name: str) -> str:
    return name.replace("%", "/")


def mangle(name: str) -> str:
    """A name as one key chunk ('/' -> '%'); an empty one (the root namespace) is '%'."""
    return name.replace("/", "%") if name else "%"


# rmw's durability enum as rmw_zenoh writes it into a token (an empty field: the default).
TRANSIENT_LOCAL = 1


def qos_chunk(depth: int, transient_local: bool = False) -> str:
    """rmw_zenoh's QoS chunk, ``<reliability>:<durability>:<history>,<depth>:<deadline>:
    <lifespan>:<liveliness>``, keep-last ``depth`` and the rest default (reliable,
    volatile, infinite durations, automatic liveliness), e.g. ``::,7:,:,:,,``."""
    return f":{TRANSIENT_LOCAL if transient_local else ''}:,{depth}:,:,:,,"


def node_token(domain_id: int, session_id: str, node_id: int, namespace: str,
               node: str) -> str:
    """The liveliness token that announces a node (kind NN, no enclave)."""
    return (f"{ADMIN_SPACE}/{domain_id}/{session_id}/{node_id}/{node_id}/NN/%/"
            f"{mangle(namespace)}/{mangle(node)}")


def endpoint_token(domain_id: int, session_id: str, node_id: int, entity_id: int,
                   kind: str, namespace: str, node: str, topic: str, dds_type: str,
                   type_hash: str, qos: str) -> str:
    """The liveliness token of a node's publisher (MP) or subscription (MS) on ``topic``."""
    return (f"{ADMIN_SPACE}/{domain_id}/{session_id}/{node_id}/{entity_id}/{kind}/%/"
            f"{mangle(namespace)}/{mangle(node)}/{mangle(normalise_topic(topic))}/"
            f"{dds_type}/{type_hash}/{qos}")


@dataclass(frozen=True)
class Endpoint:
    """A publisher, subscription, service server or client, from its liveliness token."""

    kind: str  # MP, MS, SS, SC
    topic: str  # fully qualified, e.g. /camera/rgb/image_color
    ros_type: str  # e.g. sensor_msgs/msg/Image (the DDS name as given if it is not one)
    type_hash: str
    node: str  # fully qualified node name


def parse_liveliness(key: str) -> Endpoint | None:
    """The endpoint a liveliness token announces; None for a node token or any other key."""
    chunks = key.split("/")
    if len(chunks) != _ENDPOINT_CHUNKS or chunks[0] != ADMIN_SPACE \
            or chunks[5] not in ENDPOINT_KINDS:
        return None
    namespace = _demangle(chunks[7])
    node = namespace.rstrip("/") + "/" + _demangle(chunks[8])
    dds_type = chunks[10]
    return Endpoint(kind=chunks[5], topic=normalise_topic(_demangle(chunks[9])),
                    ros_type=ros_type_name(dds_type) or dds_type, type_hash=chunks[11],
                    node=node if node.startswith("/") else "/" + node)


@dataclass(frozen=True)
class Attachment:
    """What rmw_zenoh attaches to each published message."""

    sequence_number: int
    source_timestamp_ns: int
    gid: bytes


GID_SIZE = 16


def make_attachment(sequence_number: int, source_timestamp_ns: int, gid: bytes) -> bytes:
    """What rmw_zenoh attaches to a message it publishes (``parse_attachment``'s layout)."""
    if len(gid) != GID_SIZE:
        raise ValueError(f"a publisher GID is {GID_SIZE} bytes, got {len(gid)}")
    return _ATTACHMENT.pack(sequence_number, source_timestamp_ns, GID_SIZE) + gid


def parse_attachment(data: bytes) -> Attachment:
    """An rmw_zenoh attachment; ValueError if ``data`` is not one (an older rmw_zenoh sent a
    key/value map instead)."""
    if len(data) < _ATTACHMENT.size:
        raise ValueError(f"attachment of {len(data)} bytes, expected {_ATTACHMENT.size + 16}")
    sequence, stamp, gid_size = _ATTACHMENT.unpack_from(data)
    if len(data) != _ATTACHMENT.size + gid_size:
        raise ValueError(f"attachment of {len(data)} bytes with a GID of {gid_size}")
    return Attachment(sequence, stamp, bytes(data[_ATTACHMENT.size:]))


def header_stamp(payload: bytes | memoryview, where: str) -> float:
    """The std_msgs/Header stamp (seconds) a CDR camera message starts with, read without
    decoding the rest (the pairing needs only it); ValueError naming ``where`` if the
    payload is not classic CDR."""
    order = _ENCAPSULATIONS.get(bytes(payload[:2]))
    if order is None:
        raise ValueError(f"{where}: payload does not start with a classic CDR encapsulation "
                         f"header (00 00 or 00 01), got {bytes(payload[:4]).hex(' ')}")
    if len(payload) < CDR_HEADER_SIZE + _STAMP[order].size:
        raise ValueError(f"{where}: CDR payload of {len(payload)} bytes has no header stamp")
    sec, nanosec = _STAMP[order].unpack_from(payload, CDR_HEADER_SIZE)
    return float(sec) + float(nanosec) * 1e-9

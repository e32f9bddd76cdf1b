"""Which live ROS 2 topics are a robot's colour, depth and camera_info: the configured ones,
or found among the publishers alive (rmw_zenoh's liveliness tokens) when that is certain."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

from fleetslam.datasets.rmw_zenoh import PUBLISHER, Endpoint, normalise_topic
from fleetslam.datasets.ros_messages import IMAGE_TYPES

# image_transport republishes a raw image under these sub-topics (CompressedImage, ...).
TRANSPORT_SUFFIXES = ("compressed", "compressedDepth", "theora", "zstd")


class TopicChoiceError(ValueError):
    """The live topics do not say which are colour and depth; the text lists them."""


@dataclass(frozen=True)
class CameraTopics:
    colour: str
    depth: str
    colour_info: str
    depth_info: str  # the depth topic's sibling camera_info (read if it is published)


def base_topic(topic: str) -> str:
    """The raw image topic an image_transport sub-topic republishes (itself otherwise)."""
    parent, _, last = topic.rpartition("/")
    return parent if parent and last in TRANSPORT_SUFFIXES else topic


def sibling_camera_info(image_topic: str) -> str:
    """``/camera/rgb/image_color[/compressed]`` -> ``/camera/rgb/camera_info`` (ROS's
    image_transport convention: camera_info next to the raw image)."""
    parent = base_topic(image_topic).rpartition("/")[0]
    return f"{parent}/camera_info"


def published_types(endpoints: Iterable[Endpoint]) -> dict[str, set[str]]:
    """Topic -> the types its live publishers announce."""
    topics: dict[str, set[str]] = {}
    for e in endpoints:
        if e.kind == PUBLISHER:
            topics.setdefault(e.topic, set()).add(e.ros_type)
    return topics


def describe(topics: dict[str, set[str]], only: tuple[str, ...] = ()) -> str:
    """``/a (sensor_msgs/msg/Image), /b (...)`` for messages; "none" when empty."""
    shown = [f"{t} ({', '.join(sorted(types))})" for t, types in sorted(topics.items())
             if not only or types & set(only)]
    return ", ".join(shown) if shown else "none"


def _is_depth(topic: str) -> bool:
    return "depth" in topic.lower()


def image_candidates(topics: dict[str, set[str]]) -> tuple[list[str], list[str]]:
    """(colour, depth) image topics alive: a name with "depth" is depth, every other image
    topic colour; an image_transport sub-topic whose raw image is alive is the same images
    again and is left out."""
    images = {t for t, types in topics.items() if types & set(IMAGE_TYPES)}
    distinct = sorted(t for t in images if base_topic(t) == t or base_topic(t) not in images)
    return [t for t in distinct if not _is_depth(t)], [t for t in distinct if _is_depth(t)]


def choose_topics(topics: dict[str, set[str]], rgb_topic: str = "", depth_topic: str = "",
                  camera_info_topic: str = "") -> CameraTopics:
    """The configured topics, the missing ones found among ``topics``; TopicChoiceError
    naming the live image topics when it is not exactly one colour and one depth."""
    colours, depths = image_candidates(topics)
    colour = normalise_topic(rgb_topic) if rgb_topic else ""
    depth = normalise_topic(depth_topic) if depth_topic else ""
    if not colour:
        colour = colours[0] if len(colours) == 1 else ""
    if not depth:
        depth = depths[0] if len(depths) == 1 else ""
    if not colour or not depth:
        missing = " and ".join(w for w, t in (("colour", colour), ("depth", depth)) if not t)
        raise TopicChoiceError(
            f"cannot tell the {missing} image topic: live image topics are "
            f"{describe(topics, IMAGE_TYPES)} (a name with 'depth' counts as depth); name them "
            f"with [source] rgb_topic / depth_topic")
    info = normalise_topic(camera_info_topic) if camera_info_topic else sibling_camera_info(colour)
    return CameraTopics(colour, depth, info, sibling_camera_info(depth))

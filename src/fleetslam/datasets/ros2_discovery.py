"""Which live ROS 2 topics are a robot's colour, depth and camera_info: the configured ones,
or found among the publishers alive (rmw_zenoh's liveliness tokens) when that is certain.

``preferred_images`` is the one rule, for these live topics and a bag's (datasets/bag.py),
for which of several image topics of a role a user means."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

from fleetslam.datasets.rmw_zenoh import PUBLISHER, Endpoint, normalise_topic
from fleetslam.datasets.ros_messages import IMAGE_TYPES

# image_transport republishes a raw image under these sub-topics (CompressedImage, ...).
TRANSPORT_SUFFIXES = ("compressed", "compressedDepth", "theora", "zstd")
# Depth registered to the colour camera (RealSense aligned_depth_to_color, openni
# depth_registered, Azure Kinect depth_to_rgb): the colour camera's intrinsics fit it.
ALIGNED_DEPTH_MARKERS = ("aligned", "registered", "depth_to_rgb", "depth_to_color")


class TopicChoiceError(ValueError):
    """The live topics do not say which are colour and depth; the text lists them."""


@dataclass(frozen=True)
class CameraTopics:
    colour: str
    depth: str
    colour_info: str
    depth_info: str  # the depth topic's sibling camera_info (read if it is published)
    why: str = ""  # the topics passed over and why, for the log ("" if none were)


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


def _is_aligned(topic: str) -> bool:
    return any(marker in topic.lower() for marker in ALIGNED_DEPTH_MARKERS)


def preferred_images(candidates: Iterable[str], role: str, among: Iterable[str] = ()
                     ) -> tuple[list[str], list[str]]:
    """The image topics of one role ("colour" or "depth") a user means, and the others,
    each as "TOPIC (why passed over)". An image_transport sub-topic whose raw image is in
    ``among`` (default: the candidates) is the same images again, coded; depth aligned to
    colour wins over unaligned depth, which the colour camera's intrinsics do not fit."""
    topics = sorted(set(candidates))
    present = set(among) or set(topics)
    kept = [t for t in topics if base_topic(t) == t or base_topic(t) not in present]
    passed = [f"{t} (image_transport copy of {base_topic(t)})" for t in topics
              if t not in kept]
    aligned = [t for t in kept if _is_aligned(t)] if role == "depth" else []
    if aligned and len(aligned) < len(kept):
        passed += [f"{t} (not aligned to colour)" for t in kept if t not in aligned]
        kept = aligned
    return kept, passed


def image_candidates(topics: dict[str, set[str]]) -> tuple[list[str], list[str]]:
    """(colour, depth) image topics alive that a user means (``preferred_images``): a name
    with "depth" is depth, every other image topic colour."""
    return _preferred(topics)[0]


def _preferred(topics: dict[str, set[str]]) -> tuple[tuple[list[str], list[str]],
                                                    tuple[list[str], list[str]]]:
    """(colour, depth) candidates and (colour, depth) topics passed over."""
    images = {t for t, types in topics.items() if types & set(IMAGE_TYPES)}
    colours, colours_passed = preferred_images(
        [t for t in images if not _is_depth(t)], "colour", images)
    depths, depths_passed = preferred_images([t for t in images if _is_depth(t)], "depth", images)
    return (colours, depths), (colours_passed, depths_passed)


def choose_topics(topics: dict[str, set[str]], rgb_topic: str = "", depth_topic: str = "",
                  camera_info_topic: str = "") -> CameraTopics:
    """The configured topics, the missing ones found among ``topics``; TopicChoiceError
    naming the live image topics when it is not exactly one colour and one depth."""
    (colours, depths), (colours_passed, depths_passed) = _preferred(topics)
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
    # Only what was chosen here: a configured topic passed nothing over.
    passed = [*([] if rgb_topic else colours_passed), *([] if depth_topic else depths_passed)]
    why = f"chosen over {', '.join(passed)}" if passed else ""
    return CameraTopics(colour, depth, info, sibling_camera_info(depth), why)

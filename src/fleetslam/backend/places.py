"""The keyframe database a config asks for: exact nearest neighbours
(place_recognition.py) or a bag of words on a trained vocabulary (vocabulary.py)."""

from __future__ import annotations

from fleetslam.backend.place_recognition import KeyframeDatabase
from fleetslam.backend.state import PlaceDatabase
from fleetslam.backend.vocabulary import BowDatabase
from fleetslam.config import PlaceRecognitionConfig


def make_database(config: PlaceRecognitionConfig) -> PlaceDatabase:
    """The keyframe database ``config.method`` names."""
    if config.method == "nearest_neighbour":
        return KeyframeDatabase(config)
    if config.method == "bag_of_words":
        return BowDatabase(config)
    raise ValueError(f"place_recognition.method: '{config.method}' is not one of "
                     f"'nearest_neighbour', 'bag_of_words'")

"""What a cloud worker asks of its placement, whichever decides (placement.py: Zenoh liveliness
bids; fenced_placement.py: etcd with fencing), and what a placement tells the worker back
(``Served``: the router). Both placements compose a WorkerDirectory (worker_directory.py) for
what they share: which workers are up, their loads, the election counts.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Protocol

import zenoh


class Served(Protocol):
    """The worker's side of placement: the robots it is handed and must drop (the router)."""

    def take(self, robot_id: str) -> None:
        """This worker won ``robot_id`` (called once per win, on an election thread)."""

    def give_up(self, robot_id: str) -> None:
        """Another worker serves ``robot_id`` (or this one was fenced): drop it unsaved."""

    def worth_serving(self, robot_id: str) -> bool:
        """Whether a robot whose owner went is worth taking over (the store has its
        checkpoint)."""


class Placement(ABC):
    """Which worker serves which robot, and whether this worker merges."""

    @abstractmethod
    def start(self, z: zenoh.Session, served: Served) -> "Placement":
        """Take part on ``z``; robots won go to ``served`` from now on."""

    @abstractmethod
    def close(self) -> None:
        """Give every robot back (the other workers take them from their checkpoints)."""

    @abstractmethod
    def serves(self, robot: str) -> bool:
        """Whether this worker serves ``robot`` now."""

    @abstractmethod
    def merges(self) -> bool:
        """Whether this worker runs the fleet's merger."""

    @abstractmethod
    def held(self) -> int:
        """Robots this worker serves now."""

    @abstractmethod
    def owner(self, robot: str) -> str | None:
        """The worker serving ``robot`` as this worker last heard (None: nobody)."""

    @abstractmethod
    def table(self) -> dict[str, str]:
        """Every robot served, and its worker, as this worker last heard."""

    @abstractmethod
    def unavailable(self) -> str | None:
        """Why this worker cannot be granted any robot now (None: it can)."""

    @abstractmethod
    def live_workers(self) -> list[str]:
        """The workers up (this one included), sorted."""

    @abstractmethod
    def load_scores(self, workers: list[str]) -> dict[str, float]:
        """Cores each of ``workers`` has busy, as placement weighs them."""

    @abstractmethod
    def says_full(self) -> bool:
        """Whether this worker is the one to tell a new robot that every worker is full."""

    @abstractmethod
    def claim(self, robot: str) -> None:
        """Ask to serve ``robot`` unless it is served (returns at once)."""

    @abstractmethod
    def release(self, robot: str) -> None:
        """Stop serving ``robot`` (another worker may take it)."""

    @property
    @abstractmethod
    def elections(self) -> dict[str, int]:
        """How this worker's elections went, by outcome (a copy)."""

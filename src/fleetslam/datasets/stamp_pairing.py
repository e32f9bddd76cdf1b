"""Colour and depth images of a live camera paired by their stamps as they arrive.

Each stream keeps at most ``capacity`` waiting messages (a camera whose other stream stalls
cannot grow memory). A message pairs with the nearest waiting one of the other stream when
they are at most ``tolerance_s`` apart; pairs come out in stamp order, so whatever waits
older than a pair can never pair any more and is dropped. Every message dropped unpaired is
counted.
"""

from __future__ import annotations

from collections import deque
from typing import Generic, TypeVar

T = TypeVar("T")
COLOUR, DEPTH = 0, 1


class StampPairer(Generic[T]):
    """Not thread-safe: the caller holds its lock around ``add``."""

    def __init__(self, tolerance_s: float, capacity: int) -> None:
        if capacity < 1:
            raise ValueError(f"a stream needs room for at least 1 waiting message, got {capacity}")
        self.tolerance_s = tolerance_s
        self._waiting: tuple[deque[tuple[float, T]], deque[tuple[float, T]]] = (
            deque(), deque())
        self._capacity = capacity
        self._last = float("-inf")  # stamp of the newest pair
        self.paired = 0  # pairs made
        self.unpaired = 0  # messages dropped without a partner

    def add(self, stream: int, stamp: float, item: T) -> tuple[T, T, float] | None:
        """Offer a message of ``stream`` (COLOUR or DEPTH); the (colour, depth, colour
        stamp) pair it completes, or None while it waits."""
        if stamp <= self._last:  # older than a pair already made: it can never pair
            self.unpaired += 1
            return None
        other = self._waiting[1 - stream]
        best = min(range(len(other)), key=lambda i: abs(other[i][0] - stamp), default=None)
        if best is None or abs(other[best][0] - stamp) > self.tolerance_s:
            own = self._waiting[stream]
            if len(own) == self._capacity:
                own.popleft()
                self.unpaired += 1
            own.append((stamp, item))
            return None
        partner_stamp, partner = other[best]
        # Everything waiting up to the pair is older than it: never to be paired.
        self.unpaired += best
        for _ in range(best + 1):
            other.popleft()
        own = self._waiting[stream]
        while own and own[0][0] <= stamp:
            own.popleft()
            self.unpaired += 1
        self._last = max(stamp, partner_stamp)
        self.paired += 1
        if stream == COLOUR:
            return item, partner, stamp
        return partner, item, partner_stamp

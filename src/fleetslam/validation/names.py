"""Names that become a chunk of a Zenoh key and a message header: robot and worker ids."""

from __future__ import annotations

import re

MAX_NAME_LENGTH = 64
NAME = re.compile(rf"[A-Za-z0-9_-]{{1,{MAX_NAME_LENGTH}}}")


def name_problem(name: str) -> str | None:
    """What is wrong with ``name`` as an id, or None."""
    if NAME.fullmatch(name):
        return None
    return f"must be 1..{MAX_NAME_LENGTH} characters of [A-Za-z0-9_-]"

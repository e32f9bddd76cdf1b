"""What Linux says of a process in /proc/<pid>/stat: its fields, and the CPU it has used.
Light on purpose (no numpy, no gtsam): the placement's load meter reads every process of a
worker's tree with it, and the merger's place search watches its process."""

from __future__ import annotations

import os
from pathlib import Path


def proc_stat(pid: int) -> list[str] | None:
    """The fields of /proc/<pid>/stat after the command's name (its state first); None
    where that cannot be read (another system, the process gone)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None


def stat_cpu_seconds(fields: list[str]) -> float:
    """User + system CPU seconds from ``proc_stat``'s fields."""
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def process_cpu_seconds(pid: int) -> float | None:
    """User + system CPU seconds process ``pid`` has used; None where that cannot be read."""
    fields = proc_stat(pid)
    try:
        return None if fields is None else stat_cpu_seconds(fields)
    except (IndexError, ValueError):
        return None

"""Reading a file fleetslam wrote, as one that may not be: only a regular file (opening a
FIFO to read waits for a writer for ever), never more than a limit."""

from __future__ import annotations

import os
import stat
from pathlib import Path
from typing import BinaryIO, Callable


class UnreadableFile(ValueError):
    """``where`` (the file) and ``reason`` (what is wrong with it)."""

    def __init__(self, where: str, reason: str) -> None:
        super().__init__(f"{where}: {reason}")
        self.where = where
        self.reason = reason


# Given the open file and its size, why it must not be read (None: read it).
Vet = Callable[[BinaryIO, int], "str | None"]


def read_regular(path: Path, limit: int, limit_name: str, vet: Vet | None = None) -> bytes:
    """The file's bytes; UnreadableFile if it is missing (reason "missing"), unreadable, not
    a regular file, over ``limit`` bytes (``limit_name`` says which limit, e.g. "the
    limit of 1000 (a setting)": the reason is "<size> bytes exceeds <limit_name>") or
    refused by ``vet`` (what its format says of the file before it is read whole)."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    except FileNotFoundError:
        raise UnreadableFile(str(path), "missing") from None
    except OSError as exc:
        raise UnreadableFile(str(path), f"cannot be read ({exc})") from None
    try:
        status = os.fstat(fd)
        if not stat.S_ISREG(status.st_mode):
            raise UnreadableFile(str(path), "not a regular file (a FIFO, a device or a "
                                            "folder?), so not one fleetslam wrote")
        if status.st_size > limit:
            raise UnreadableFile(str(path), f"{status.st_size} bytes exceeds {limit_name}")
        with os.fdopen(fd, "rb") as f:
            fd = -1  # the file object closes it now
            if vet is not None and (problem := vet(f, status.st_size)) is not None:
                raise UnreadableFile(str(path), problem)
            f.seek(0)
            # What the file holds, never more than the limit (read() allocates what it is
            # asked for; a file growing meanwhile is cut, and refused by its reader).
            return f.read(min(status.st_size + 1, limit + 1))
    except OSError as exc:
        raise UnreadableFile(str(path), f"cannot be read ({exc})") from None
    finally:
        if fd >= 0:
            os.close(fd)

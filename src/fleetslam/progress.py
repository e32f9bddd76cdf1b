"""Progress lines for long work: done/total, rate, ETA, on one refreshed stderr line."""

from __future__ import annotations

import sys
import time
from typing import TextIO


class Progress:
    def __init__(self, label: str, total: int | None, unit: str = "frames",
                 stream: TextIO | None = None,
                 enabled: bool = True, min_interval_s: float = 0.25) -> None:
        self.label = label
        self.total = total
        self.unit = unit
        self.stream = stream or sys.stderr
        self.enabled = enabled
        self.start = time.perf_counter()
        self._last_print = 0.0
        self._finished = False
        self.min_interval_s = min_interval_s
        # A terminal gets one refreshed line; a log file gets occasional full lines.
        self._tty = hasattr(self.stream, "isatty") and self.stream.isatty()

    def update(self, done: int, note: str = "") -> None:
        if not self.enabled:
            return
        now = time.perf_counter()
        # No total (a live camera): no ETA; the caller's last line is not marked final.
        final = self.total is not None and done >= self.total
        if final and self._finished:
            return  # the final line is printed once
        self._finished = final
        interval = self.min_interval_s if self._tty else 5.0
        if not final and now - self._last_print < interval:
            return
        self._last_print = now
        elapsed = now - self.start
        rate = done / elapsed if elapsed > 0 else 0.0
        if self.total is None:
            line = f"{self.label}: {done} {self.unit}  {rate:5.1f}/s"
        else:
            eta = f"{(self.total - done) / rate:5.0f}s" if rate > 0 else "    -"
            line = f"{self.label}: {done}/{self.total} {self.unit}  {rate:5.1f}/s  ETA {eta}"
        line += f"  {note}" if note else ""
        if self._tty:
            self.stream.write("\r" + line.ljust(100) + ("\n" if final else ""))
        else:
            self.stream.write(line + "\n")
        self.stream.flush()

    def finish(self, done: int, note: str = "") -> None:
        """The last line, for work whose total was not known (a live camera)."""
        if self.total is None:
            self.total = done
        self.update(done, note)

    def message(self, text: str) -> None:
        if self.enabled:
            self.stream.write(("\n" if self._tty else "") + text + "\n")
            self.stream.flush()

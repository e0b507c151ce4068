"""A minimal progress bar on stderr for long commands (no dependency, quiet when not a terminal)."""

from __future__ import annotations

import sys
import time


class Progress:
    """``with Progress(total, "simulating") as p: ... p.advance()`` — redraws at most 10×/s."""

    def __init__(self, total: int, label: str, stream=None, enabled: bool | None = None):
        self.total = max(int(total), 1)
        self.label = label
        self.done = 0
        self.stream = stream or sys.stderr
        self.enabled = self.stream.isatty() if enabled is None else enabled
        self._last = 0.0
        self._t0 = time.monotonic()

    def __enter__(self) -> "Progress":
        self._draw(force=True)
        return self

    def advance(self, n: int = 1) -> None:
        self.done += n
        self._draw()

    def _draw(self, force: bool = False) -> None:
        now = time.monotonic()
        if not self.enabled or (not force and now - self._last < 0.1 and self.done < self.total):
            return
        self._last = now
        frac = min(self.done / self.total, 1.0)
        bar = "#" * int(30 * frac)
        self.stream.write(f"\r{self.label} [{bar:<30}] {self.done}/{self.total} {now - self._t0:5.1f}s")
        self.stream.flush()

    def __exit__(self, *exc) -> None:
        self._draw(force=True)
        if self.enabled:
            self.stream.write("\n")
        elif exc[0] is None:
            self.stream.write(f"{self.label}: {self.done}/{self.total} in {time.monotonic() - self._t0:.1f}s\n")
        self.stream.flush()

"""Progress of long commands on stderr: a total and an estimate of the time left (no dependency).

On a terminal one line is redrawn in place; elsewhere (a log file, CI, a pipe) a line is written
every ``every_s`` seconds, so that a long wait is never silent.
"""

from __future__ import annotations

import sys
import time

REDRAW_S = 0.1  # a terminal line is redrawn at most this often
EVERY_S = 5.0  # when not on a terminal, a line this often


def format_seconds(s: float) -> str:
    """``"~25 s"``, ``"~3 min"``: an estimate, rounded as one."""
    if s < 90:
        return f"~{max(1, round(s))} s"
    return f"~{round(s / 60)} min"


class Progress:
    """``with Progress(total, "passes") as p: ... p.update(done, note=..., left_s=...)``.

    Each line reads ``<label> <done>/<total> <unit>, <note>, ~<left> left``. The time left is the
    caller's estimate (``left_s``) when it has one, else extrapolated from the rate so far.

    ``enabled``: None follows the stream (a terminal: a line redrawn in place; otherwise: a line every
    ``every_s`` seconds), True forces the terminal style, False is silent.
    """

    def __init__(self, total: int, label: str, stream=None, enabled: bool | None = None, unit: str = "",
                 every_s: float = EVERY_S, clock=time.monotonic):
        self.total = max(int(total), 1)
        self.label, self.unit, self.every_s, self.clock = label, unit, every_s, clock
        self.done = 0
        self.note = ""
        self.left_s: float | None = None
        self.stream = stream or sys.stderr
        tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.silent = enabled is False
        self.inplace = bool(enabled) or (enabled is None and tty)
        self._t0 = clock()
        self._last = -float("inf")
        self._width = 0

    def __enter__(self) -> Progress:
        self._draw(force=True)
        return self

    def advance(self, n: int = 1) -> None:
        self.update(self.done + n)

    def update(self, done: int | None = None, note: str | None = None, left_s: float | None = None) -> None:
        """Set what is done (of ``total``), a note (e.g. the calibration round) and the caller's
        estimate of the seconds left (None: extrapolate from the rate so far)."""
        if done is not None:
            self.done = int(done)
        if note is not None:
            self.note = note
        self.left_s = left_s
        self._draw()

    def line(self) -> str:
        elapsed = self.clock() - self._t0
        parts = [f"{self.label} {self.done}/{self.total}" + (f" {self.unit}" if self.unit else "")]
        if self.note:
            parts.append(self.note)
        left = self.left_s
        if left is None and 0 < self.done < self.total:
            left = elapsed * (self.total - self.done) / self.done
        if left is not None and (self.done < self.total or self.left_s is not None):
            parts.append(f"{format_seconds(left)} left")
        parts.append(f"{elapsed:.0f} s so far")
        return ", ".join(parts)

    def _draw(self, force: bool = False) -> None:
        if self.silent:
            return
        now = self.clock()
        if not force and now - self._last < (REDRAW_S if self.inplace else self.every_s):
            return
        self._last = now
        text = self.line()
        if self.inplace:
            self.stream.write("\r" + text.ljust(self._width))
            self._width = len(text)
        else:
            self.stream.write(text + "\n")
        self.stream.flush()

    def __exit__(self, *exc) -> None:
        if self.silent:
            return
        elapsed = self.clock() - self._t0
        end = f"{self.label} {self.done}/{self.total}" + (f" {self.unit}" if self.unit else "") + \
            (f", {self.note}" if self.note else "") + f" in {elapsed:.1f} s"
        if self.inplace:
            self.stream.write("\r" + end.ljust(self._width) + "\n")
        elif exc[0] is None:
            self.stream.write(end + "\n")
        self.stream.flush()

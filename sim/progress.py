"""One progress line for long work: done / total, rate and ETA.

``Progress(total, done, label, unit)`` prints to stderr in place on a terminal (every 0.2 s) and
otherwise as a new line every 5 s (a log file gets a readable history), always at the start and
at the end. ``update(n)`` adds ``n`` items; ``rate_scale`` turns items into the unit shown
(a training shows iterations done and pairs per second: ``rate_unit="pairs/s"``,
``rate_scale=batch_size``). Used by ``ctxreg simulate``, ``train``, ``evaluate`` and ``study``.
"""

from __future__ import annotations

import math
import sys
import time

__all__ = ["Progress"]


class Progress:
    """Items done, rate and ETA on stderr: in place on a terminal, else a line every 5 s.

    Args:
        total: items in all; done: items already done (a resumed run), not counted in the rate.
        label: what is running (the line's start); unit: the items' name ("images", "iterations").
        rate_unit: the rate's unit (default ``"<unit>/s"``); rate_scale: rate units per item.
    """

    def __init__(self, total: int, done: int, label: str, unit: str = "images", *, rate_unit: str | None = None,
                 rate_scale: float = 1.0):
        self.total, self.done, self.label, self.unit = int(total), int(done), label, unit
        self.rate_unit = rate_unit or f"{unit[:3]}/s"
        self.rate_scale = float(rate_scale)
        self.start_done, self.t0, self.last = self.done, time.monotonic(), 0.0
        self.tty = sys.stderr.isatty()
        self.show(force=True)

    def update(self, n: int = 1) -> None:
        self.done += n
        self.show(force=self.done >= self.total)

    def line(self) -> str:
        """The progress line (without the carriage return)."""
        now = time.monotonic()
        rate = (self.done - self.start_done) / max(now - self.t0, 1e-9)
        eta = (self.total - self.done) / rate if rate > 0 else float("nan")
        pct = 100.0 * self.done / max(self.total, 1)
        eta_text = "--" if not math.isfinite(eta) else time.strftime("%H:%M:%S", time.gmtime(eta))
        return (f"{self.label}: {self.done}/{self.total} {self.unit} ({pct:5.1f} %), "
                f"{rate * self.rate_scale:6.1f} {self.rate_unit}, ETA {eta_text}")

    def show(self, force: bool = False) -> None:
        now = time.monotonic()
        if not force and now - self.last < (0.2 if self.tty else 5.0):
            return
        self.last = now
        line = self.line()
        print(("\r" + line) if self.tty else line, end="" if self.tty else "\n", file=sys.stderr, flush=True)
        if self.tty and self.done >= self.total:
            print(file=sys.stderr)

"""One progress line for long work: done / total, rate and ETA.

``Progress(total, done, label, unit)`` prints to stderr in place on a terminal (every 0.2 s) and
otherwise as a new line every 5 s (a log file gets a readable history), always at the start and
at the end. ``update(n)`` adds ``n`` items; ``rate_scale`` turns items into the unit shown
(a training shows iterations done and pairs per second: ``rate_unit="pairs/s"``,
``rate_scale=batch_size``). Used by ``ctxreg simulate``, ``train``, ``evaluate`` and ``study``.

:class:`StageClock` times the stages of one piece of work (wall seconds by stage name), and
:func:`process_seconds` says how long this process has run (its start-up and imports included):
``ctxreg register`` keeps both in ``result.json`` (``timings_s``) and prints them with ``--verbose``.
"""

from __future__ import annotations

import math
import sys
import time

__all__ = ["Progress", "StageClock", "process_seconds"]


def process_seconds() -> float | None:
    """Wall seconds since this process started (its interpreter's start-up and imports included),
    from ``/proc`` (Linux); None where that is not readable."""
    import os

    try:
        with open("/proc/self/stat") as f:
            start_ticks = int(f.read().rsplit(")", 1)[1].split()[19])  # field 22: starttime, after the name
        with open("/proc/uptime") as f:
            uptime = float(f.read().split()[0])
        return max(uptime - start_ticks / os.sysconf("SC_CLK_TCK"), 0.0)
    except (OSError, ValueError, IndexError):
        return None


class StageClock:
    """Wall seconds of named stages, disjoint, in the order they finished.

    ``with clock("ct"): ...`` adds the block's seconds to stage ``"ct"`` (a stage that runs twice
    sums). A stage entered inside another is its own: the outer stage's seconds leave it out, so
    the stages add up to the wall time they cover. ``clock.seconds`` is the ``{stage: s}`` dict,
    ``clock.lines()`` one line per stage.

    Example::

        >>> clock = StageClock()
        >>> with clock("register"):
        ...     with clock("polarity"):
        ...         pass
        >>> list(clock.seconds)
        ['polarity', 'register']
    """

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self._open: list[_Stage] = []

    def __call__(self, stage: str):
        return _Stage(self, stage)

    def add(self, stage: str, seconds: float) -> None:
        self.seconds[stage] = self.seconds.get(stage, 0.0) + float(seconds)

    def lines(self) -> list[str]:
        """``"stage: 1.23 s"`` per stage."""
        return [f"{k}: {v:.2f} s" for k, v in self.seconds.items()]


class _Stage:
    def __init__(self, clock: StageClock, stage: str) -> None:
        self.clock, self.stage = clock, stage
        self.inner = 0.0  # seconds of the stages entered inside this one

    def __enter__(self):
        self.t0 = time.perf_counter()
        self.clock._open.append(self)
        return self

    def __exit__(self, *exc) -> None:
        elapsed = time.perf_counter() - self.t0
        self.clock._open.pop()
        if self.clock._open:
            self.clock._open[-1].inner += elapsed
        self.clock.add(self.stage, elapsed - self.inner)


class Progress:
    """Items done, rate and ETA on stderr: in place on a terminal, else a line every 5 s.

    Args:
        total: items in all; done: items already done (a resumed run), not counted in the rate.
        label: what is running (the line's start); unit: the items' name ("images", "iterations").
        rate_unit: the rate's unit (default ``"<unit>/s"``); rate_scale: rate units per item.
        time_limit_s: the work stops after this many seconds (s) if it has not ended before:
            the ETA and the percentage then count the time (a training with ``--stop-after``).
    """

    def __init__(self, total: int, done: int, label: str, unit: str = "images", *, rate_unit: str | None = None,
                 rate_scale: float = 1.0, time_limit_s: float | None = None):
        self.total, self.done, self.label, self.unit = int(total), int(done), label, unit
        self.time_limit_s = time_limit_s
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
        done, share = f"{self.done}/{self.total}", ""
        if self.time_limit_s is not None:  # the work ends at a time limit first: ETA and share by time
            elapsed = now - self.t0
            left = max(self.time_limit_s - elapsed, 0.0)
            if not math.isfinite(eta) or left < eta:
                eta, pct = left, 100.0 * min(elapsed / self.time_limit_s, 1.0)
                done, share = f"{self.done}", f" of {self.time_limit_s / 60:.1f} min"
        eta_text = "--" if not math.isfinite(eta) else time.strftime("%H:%M:%S", time.gmtime(eta))
        return (f"{self.label}: {done} {self.unit} ({pct:5.1f} %{share}), "
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

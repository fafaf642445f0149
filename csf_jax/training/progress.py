"""Progress lines of the offline stage on stderr (data generation, training).

On a terminal, one line rewritten in place (``\\r``). Anywhere else (a log file, a pipe, captured
output) a ``\\r`` would pile every update into one unreadable line, so each report is a plain line
instead, one per ``PLAIN_EVERY`` of the run and one at its end: a log file reads as a history.
Every line shows the average rate since the run's first report (the first report's time holds the
compilation, so it is left out) and the time left at that rate.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable

PLAIN_EVERY = 0.05
"""The fraction of a run between two plain lines (5%)."""


def is_terminal(stream) -> bool:
    """Whether ``stream`` is an interactive terminal (False for files, pipes, captured output and
    closed streams)."""
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError, OSError):
        return False


def duration(seconds: float) -> str:
    """``seconds`` for a reader: "42 s", "3 min 05 s", "2 h 07 min"."""
    s = max(0, int(round(seconds)))
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60:02d} s"
    return f"{s // 3600} h {s % 3600 // 60:02d} min"


class Progress:
    """The progress of one run of ``total`` units (steps, trajectories) from ``start`` (a resumed
    run's first count), reported on ``stream`` (default: ``sys.stderr`` at each report).

    label: the line's head, "[train double_well]".
    unit: the units' name in the rate ("steps").
    per_unit: optional ``(factor, name)``: a second rate, ``factor`` per unit ("sets").
    verbose: False prints nothing.
    clock: seconds, monotonic (``time.perf_counter``).
    """

    def __init__(self, label: str, total: int, start: int = 0, *, unit: str = "steps",
                 per_unit: tuple[float, str] | None = None, verbose: bool = True, stream=None,
                 clock: Callable[[], float] = time.perf_counter):
        self.label, self.total, self.unit, self.per_unit = label, int(total), unit, per_unit
        self.verbose, self._stream, self.clock = verbose, stream, clock
        self._mark: tuple[int, float] | None = None
        self._next_plain = start  # the count from which the next plain line is due
        self._open = 0  # the length of the terminal line being rewritten, 0 if none

    @property
    def stream(self):
        return sys.stderr if self._stream is None else self._stream

    def rate(self, count: int) -> float | None:
        """Units per second since the first report, or None before a second report."""
        if self._mark is None or count <= self._mark[0]:
            return None
        elapsed = self.clock() - self._mark[1]
        return (count - self._mark[0]) / elapsed if elapsed > 0 else None

    def report(self, count: int, detail: str = "") -> None:
        """``count`` units done; ``detail`` (the loss, say) goes after the count. The first report
        marks where the average rate is measured from."""
        if not self.verbose:
            return
        rate = self.rate(count)
        if self._mark is None:
            self._mark = (count, self.clock())
        terminal = is_terminal(self.stream)
        if not terminal and count < self._next_plain and count < self.total:
            return
        self._next_plain = count + max(1, int(PLAIN_EVERY * self.total))
        line = f"{self.label} {count}/{self.total} {self.unit} ({count / self.total:.0%})"
        if detail:
            line += f" {detail}"
        if rate is not None:
            line += f", {rate:.1f} {self.unit}/s"
            if self.per_unit is not None:
                line += f" ({rate * self.per_unit[0]:.0f} {self.per_unit[1]}/s)"
            if count < self.total:
                line += f", ETA {duration((self.total - count) / rate)}"
        if terminal:
            print("\r" + line.ljust(self._open), end="", file=self.stream, flush=True)
            self._open = len(line)
        else:
            print(line, file=self.stream, flush=True)

    def note(self, text: str, count: int) -> None:
        """An event of the run at ``count`` (a validation loss): appended to the terminal line,
        else a line of its own."""
        if not self.verbose:
            return
        if is_terminal(self.stream):
            print(f"  {text}", end="", file=self.stream, flush=True)
            self._open += 2 + len(text)
        else:
            print(f"{self.label} {count}/{self.total} {self.unit}: {text}", file=self.stream,
                  flush=True)

    def close(self) -> None:
        """End the terminal line, if one is open."""
        if self.verbose and self._open:
            print(file=self.stream, flush=True)
            self._open = 0

"""Progress of long loops (render tiles, fit steps): a live tqdm bar on a terminal, a few
plain lines in a file or a pipe.

`Progress(total, label, enabled)` has the interface of the renderer's first bar:
`update(done)` with the count done so far (not an increment). On a terminal it draws a tqdm
bar; otherwise (a log file, a pipe, a CI console, a test's captured stderr) it writes whole
lines and only a few of them: the first update, each quarter of the way, at most one a
minute in between, and the last, instead of hundreds of carriage-return frames.
"""

from __future__ import annotations

import sys
import time
from typing import Any, TextIO

__all__ = ["Progress", "is_terminal"]

QUARTERS = 4  # plain lines at each 1/QUARTERS of the way
QUIET_SECS = 60.0  # and at least one a minute


def is_terminal(stream: TextIO) -> bool:
    """Whether `stream` is an interactive terminal (where a live bar can redraw itself)."""
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # no isatty, or closed
        return False


def _columns(stream: TextIO) -> int:
    """The width of the terminal `stream` writes to (0 where unknown)."""
    import os

    try:
        return os.get_terminal_size(stream.fileno()).columns
    except (AttributeError, ValueError, OSError):
        return 0


def _fmt(v: Any) -> str:
    return f"{v:.4g}" if isinstance(v, float) else str(v)


class Progress:
    """A progress report over `total` units of work (tiles, steps).

    **Arguments:**

    - `total`: the count at completion.
    - `label`: what is being done (`"rendering"`).
    - `enabled`: `False` makes every call a no-op.
    - `unit`: what is counted (`"tiles"`).
    - `file`: the stream (default: `sys.stderr` at construction).
    - `every_line`: in plain mode, write the `line=` of every update (a fit's steps, each
      one line of parameters), not only the milestones.
    """

    def __init__(
        self,
        total: int,
        label: str = "",
        enabled: bool = True,
        *,
        unit: str = "tiles",
        file: TextIO | None = None,
        every_line: bool = False,
    ):
        self.total, self.label, self.enabled, self.unit = max(int(total), 1), label, enabled, unit
        self.file = sys.stderr if file is None else file
        self.every_line = every_line
        self.t0 = time.perf_counter()
        self.done = 0
        self._bar = None
        self._last_line = -float("inf")  # time of the last plain line
        self._next_mark = 0  # the next quarter a plain line is due at
        self._closed = False
        if enabled and is_terminal(self.file):
            from tqdm import tqdm

            sized = _columns(self.file) >= 20  # a pty may report 0 columns: then 80
            self._bar = tqdm(
                total=self.total,
                desc=label or None,
                unit=unit or "it",
                file=self.file,
                leave=True,
                dynamic_ncols=sized,
                ncols=None if sized else 80,
                nrows=None if sized else 24,
                mininterval=0.2,
            )

    def update(self, done: int, line: str | None = None, **info: Any) -> None:
        """Report `done` units finished so far; `info` (e.g. `loss=...`) is shown beside the
        count, `line` is the plain line of this update in `every_line` mode."""
        if not self.enabled or self._closed:
            return
        done = min(int(done), self.total)
        if self._bar is not None:
            if info:
                self._bar.set_postfix({k: _fmt(v) for k, v in info.items()}, refresh=False)
            self._bar.update(done - self._bar.n)
            self.done = done
            if done >= self.total:
                self.close()
            return
        last = done >= self.total
        self.done = done
        now = time.perf_counter()
        due = done >= self._next_mark * self.total / QUARTERS  # (mark 0: the first update)
        if self.every_line and line is not None:
            self._print(line)
        elif last or due or now - self._last_line >= QUIET_SECS:
            self._print(self._status(done, now, info))
        while self._next_mark * self.total / QUARTERS <= done:
            self._next_mark += 1
        if last:
            self.close()

    def write(self, line: str) -> None:
        """A line of its own (above the bar on a terminal)."""
        if not self.enabled:
            return
        if self._bar is not None:
            self._bar.write(line, file=self.file)
        else:
            self._print(line)

    def close(self) -> None:
        """Finish the report (a terminal's bar stays on screen)."""
        if self._closed:
            return
        self._closed = True
        if self._bar is not None:
            self._bar.close()

    def _status(self, done: int, now: float, info: dict) -> str:
        dt = now - self.t0
        pct = 100.0 * done / self.total
        text = f"{self.label + ': ' if self.label else ''}{done}/{self.total} {self.unit} "
        text += f"({pct:.0f}%) {dt:.1f} s"
        if 0 < done < self.total:
            text += f", about {dt * (self.total - done) / done:.0f} s left"
        if info:
            text += "  " + "  ".join(f"{k} {_fmt(v)}" for k, v in info.items())
        return text

    def _print(self, text: str) -> None:
        print(text, file=self.file, flush=True)
        self._last_line = time.perf_counter()

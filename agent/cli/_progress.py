"""Progress of long steps on a terminal: one status line on stderr, rewritten in place.

Shown only when stderr is a terminal and the command does not print ``--json``; nothing
is written otherwise (pipes, files, machines). The line appears after ``delay`` seconds
(a step that ends sooner stays silent) and is refreshed at most every ``interval``
seconds; :meth:`ProgressLine.close` erases it.

Examples
--------
>>> import io
>>> line = ProgressLine("design", stream=io.StringIO())     # not a terminal: silent
>>> line.note("designing"); line.close(); line.stream.getvalue()
''
"""

from __future__ import annotations

import sys
import time

__all__ = ["ProgressLine", "format_design_progress"]


def format_design_progress(p) -> str:
    """One line for a :class:`design.gain_design.DesignProgress`."""
    name = "rho" if p.quantity == "rho" else "MSE"
    if p.value != p.value:              # nan: a stage without iterations (certifying)
        text = p.stage
    else:
        text = (f"{p.stage}: iteration {p.iteration}/{p.max_iter}, {name} "
                f"{_num(p.value)}")
    if p.best is not None:
        text += f" (best so far {_num(p.best)})"
    text += f", {p.elapsed:.1f} s"
    if p.time_left is not None:
        text += f", {p.time_left:.0f} s left of --time-limit"
    return text


def _num(x) -> str:
    if x != x or x in (float("inf"), float("-inf")):
        return "unstable" if x == float("inf") else str(x)
    return f"{x:.5g}"


class ProgressLine:
    """A self-overwriting status line on a terminal.

    Parameters
    ----------
    label : str, printed first (the command)
    stream : text stream, default stderr
    enabled : bool or None; None: only when ``stream`` is a terminal. False (e.g. with
        ``--json``) silences it.
    delay, interval : seconds before the first line, and between two refreshes
    """

    def __init__(self, label: str, stream=None, enabled=None, delay: float = 0.5,
                 interval: float = 0.1):
        self.stream = sys.stderr if stream is None else stream
        tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.enabled = tty if enabled is None else (bool(enabled) and tty)
        self.label, self.delay, self.interval = label, delay, interval
        self.t0 = time.monotonic()
        self.last = 0.0
        self.width = 0
        self.context = ""

    def design(self, progress) -> None:
        """``progress=`` callable of :func:`design.gain_design.design_gains`."""
        self.update(format_design_progress(progress))

    def simulation(self, done: int, total: int) -> None:
        """``progress=`` callable of :func:`design.simulate.simulate`."""
        self.update(f"simulating: {done}/{total}")

    def update(self, text: str) -> None:
        if not self.enabled:
            return
        now = time.monotonic()
        if now - self.t0 < self.delay or now - self.last < self.interval:
            return
        self.last = now
        line = f"{self.label}: " + (f"{self.context}; " if self.context else "") + text
        cols = 200
        try:
            import shutil

            cols = shutil.get_terminal_size((200, 24)).columns
        except (OSError, ValueError):      # pragma: no cover - no terminal size
            pass
        line = line[:max(cols - 1, 20)]
        self.stream.write("\r" + line + " " * max(self.width - len(line), 0))
        self.stream.flush()
        self.width = len(line)

    def note(self, text: str) -> None:
        """A line that stays (a finished step), printed above the status line."""
        if not self.enabled:
            return
        self._erase()
        self.stream.write(text + "\n")
        self.stream.flush()

    def _erase(self) -> None:
        if self.width:
            self.stream.write("\r" + " " * self.width + "\r")
            self.stream.flush()
            self.width = 0

    def close(self) -> None:
        """Erase the status line."""
        if self.enabled:
            self._erase()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


class ProgressBar:
    """A one-line progress bar on stderr, shown only on a terminal after a short delay."""

    def __init__(self, label="simulate", stream=None, delay=0.5, width=30):
        self.stream = sys.stderr if stream is None else stream
        self.enabled = bool(getattr(self.stream, "isatty", lambda: False)())
        self.label, self.delay, self.width = label, delay, width
        self.t0 = time.monotonic()
        self.last = 0.0
        self.shown = False

    def __call__(self, done, total):
        if not self.enabled:
            return
        now = time.monotonic()
        if now - self.t0 < self.delay or (now - self.last < 0.1 and done < total):
            return
        self.last = now
        frac = done / total if total else 1.0
        bar = "#" * int(self.width * frac)
        self.stream.write(f"\r{self.label} [{bar:<{self.width}}] {done}/{total}")
        self.stream.flush()
        self.shown = True

    def close(self):
        if self.shown:
            self.stream.write("\r" + " " * (self.width + len(self.label) + 30) + "\r")
            self.stream.flush()

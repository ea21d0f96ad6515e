"""A log that a flood of messages cannot fill: lines are shortened and rate-limited.

A process logs one line per rejected control message, per accepted role, ... Any sender on
the mesh can cause such lines, so each line is cut to ``max_chars`` and at most ``burst``
lines pass at once, then one per ``1 / rate`` seconds (a token bucket); the lines held back
are counted and the count is reported with the next line that passes.

Examples
--------
>>> import io
>>> out = io.StringIO()
>>> t = [0.0]
>>> log = LogLimiter(out, burst=2, rate=1.0, max_chars=20, clock=lambda: t[0])
>>> [log.say(f"rejected message {i} " + "x" * 50) for i in range(5)]
[True, True, False, False, False]
>>> t[0] = 10.0
>>> log.say("later")
True
>>> print(out.getvalue(), end="")
rejected message ...
rejected message ...
later (3 similar lines suppressed)
"""

from __future__ import annotations

import time

from broker_free_net.codec import shorten

__all__ = ["LogLimiter"]


class LogLimiter:
    """Writes shortened lines to ``log``, at most ``burst`` at once and ``rate`` per second."""

    def __init__(self, log, burst: int = 20, rate: float = 1.0, max_chars: int = 300,
                 clock=time.monotonic):
        if burst < 1 or not rate > 0 or max_chars < 4:
            raise ValueError("burst >= 1, rate > 0 and max_chars >= 4 are required")
        self.log = log
        self.burst = burst
        self.rate = rate
        self.max_chars = max_chars
        self.clock = clock
        self.tokens = float(burst)
        self.suppressed = 0      # held back since the last line written
        self.suppressed_total = 0
        self._last = clock()

    def say(self, text: str) -> bool:
        """Write ``text`` (shortened) if the budget allows; return whether it was written."""
        now = self.clock()
        self.tokens = min(float(self.burst), self.tokens + (now - self._last) * self.rate)
        self._last = now
        if self.tokens < 1.0:
            self.suppressed += 1
            self.suppressed_total += 1
            return False
        self.tokens -= 1.0
        line = shorten(text, self.max_chars)
        if self.suppressed:
            line += f" ({self.suppressed} similar lines suppressed)"
            self.suppressed = 0
        print(line, file=self.log, flush=True)
        return True

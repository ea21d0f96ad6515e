"""What a live run says on the terminal: its progress on stderr and, once it is over, its
summary on stdout (``socmon up``; ``socmon chaos`` shares the progress lines).

The progress is told through a ``say(text)`` callable (:func:`say_on_stderr`), the one
:func:`agent.run.setup.live_run` and :func:`agent.run.chaos.live_chaos` take; the
summary is :func:`finished_run_text`.
"""

from __future__ import annotations

import json
import sys

__all__ = ["say_on_stderr", "finished_run_text"]


def say_on_stderr(prog: str, quiet: bool = False):
    """``say(text)``: print ``prog: text`` on stderr at once (flushed), nothing when
    ``quiet``.

    >>> import contextlib, io
    >>> err = io.StringIO()
    >>> with contextlib.redirect_stderr(err):
    ...     say_on_stderr("up")("step 0/60"); say_on_stderr("up", quiet=True)("step 50/60")
    >>> err.getvalue()
    'up: step 0/60\\n'
    """
    def say(text):
        if not quiet:
            print(f"{prog}: {text}", file=sys.stderr, flush=True)

    return say


def finished_run_text(done, as_json: bool = False) -> str:
    """What ``socmon up`` prints on stdout of the finished run ``done`` (an
    :class:`agent.run.setup.FinishedRun`): its summary as JSON, or its headline
    (:func:`agent.run.summary.headline_lines`)."""
    from agent.run.jsonable import to_jsonable
    from agent.run.summary import headline_lines

    if as_json:
        return json.dumps(to_jsonable(done.summary), indent=2)
    lines = headline_lines(done.summary, done.config.scenario)
    if getattr(done.config, "secure", False):
        lines.insert(1, "  secured (--secure): mutual TLS and access control on every process, "
                        f"keys in {done.config.out / 'keys'}")
    return "\n".join(lines)

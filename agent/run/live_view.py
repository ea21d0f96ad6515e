"""The terminal view of a run being recorded (:meth:`agent.run.recorder.Recorder.view`).

Three forms, one content: on a terminal the view is redrawn in place (one line for the
run, one per agent, one per verdict); elsewhere one plain line per update; with
``--json`` one JSON object per line (``"kind": "view"``).

Examples
--------
>>> import io
>>> view = {"run": "demo", "step": 12, "mse_step": 11, "mse": 0.5, "drops": 1, "late": 0,
...         "malformed": 0, "roster": [1, 2], "epoch": 0, "failures": [],
...         "agents": {1: {"step": 11, "active": True, "epoch": 0, "mse": 0.4, "drops": 1,
...                        "late": 0, "malformed": 0}}}
>>> print(format_line(view))
run demo  step 12  mse 0.5 (step 11; - over the last 100 steps)  drops 1  late 0  malformed 0  roster 1,2 (epoch 0)
>>> out = io.StringIO(); LiveView(out, "json", interval=0).show(view); out.getvalue()[:51]
'{"schema_version": 1, "kind": "view", "run": "demo"'
"""

from __future__ import annotations

import json
import time

from agent.run.jsonable import to_jsonable, versioned

__all__ = ["LiveView", "format_line", "format_lines", "over_last"]


def _num(x) -> str:
    return "-" if x is None else f"{x:.4g}"


def over_last(view: dict) -> str:
    """The steps the view's ``mse_last100`` covers and, when fewer, the samples it is
    the mean of (``up --record-every 5`` keeps every 5th step's states).

    >>> over_last({"mse_last100_steps": 100, "mse_last100_samples": 20})
    'over the last 100 steps (20 samples)'
    >>> over_last({"mse_last100_steps": 31, "mse_last100_samples": 31})
    'over the last 31 steps'
    """
    steps = view.get("mse_last100_steps", 100)
    samples = view.get("mse_last100_samples", steps)
    return f"over the last {steps} steps" + (f" ({samples} samples)" if samples != steps
                                             else "")


def format_line(view: dict) -> str:
    """The run in one line."""
    return (f"run {view['run']}  step {view['step']}  mse {_num(view['mse'])}"
            + (f" (step {view['mse_step']}; {_num(view.get('mse_last100'))} "
               f"{over_last(view)})" if view["mse_step"] is not None else "")
            + f"  drops {view['drops']}  late {view['late']}  malformed {view['malformed']}"
            + f"  roster {','.join(map(str, view['roster']))} (epoch {view['epoch']})"
            + "".join(f"  FAILED agent {f['agent']} ({f['cause']}, step {f['step']})"
                      for f in view["failures"])
            + _no_monitor(view, "  "))


def _no_monitor(view: dict, sep: str) -> str:
    since = view.get("no_monitor_since")
    return ("" if since is None else
            f"{sep}NO MONITOR ALIVE since step {since}: failures are neither detected nor "
            "recovered")


def format_lines(view: dict) -> list:
    """The run, then one line per agent, then one per verdict."""
    lines = [format_line(view).split("  FAILED")[0].split("  NO MONITOR")[0],
             f"{'agent':>5} {'step':>7} {'role':>8} {'epoch':>5} {'mse':>10} {'drops':>6} "
             f"{'late':>6} {'malformed':>9}"]
    for a, r in sorted(view["agents"].items()):
        role = {True: "active", False: "standby", None: "-"}[r["active"]]
        lines.append(f"{a:>5} {'-' if r['step'] is None else r['step']:>7} {role:>8} "
                     f"{'-' if r['epoch'] is None else r['epoch']:>5} {_num(r['mse']):>10} "
                     f"{r['drops']:>6} {r['late']:>6} {r['malformed']:>9}")
    for f in view["failures"]:
        lines.append(f"verdict: agent {f['agent']} {f['cause']} at step {f['step']}")
    if view.get("no_monitor_since") is not None:
        lines.append(_no_monitor(view, ""))
    return lines


class LiveView:
    """Show views on ``stream``: ``mode`` ``"tty"`` (redrawn in place), ``"plain"`` or
    ``"json"``; at most one update per ``interval`` seconds (the last one is always
    shown by :meth:`close`)."""

    def __init__(self, stream, mode: str, interval: float):
        if mode not in ("tty", "plain", "json"):
            raise ValueError(f"mode: {mode!r} is not tty, plain or json")
        self.stream, self.mode, self.interval = stream, mode, interval
        self._drawn = 0            # lines drawn by the last tty update
        self._next = 0.0
        self._last = None
        self._text = None          # the last plain or JSON line written

    def show(self, view: dict, force: bool = False) -> None:
        now = time.monotonic()
        self._last = view
        if not force and now < self._next:
            return
        self._next = now + self.interval
        if self.mode in ("json", "plain"):
            text = (json.dumps(to_jsonable(versioned({"kind": "view", **view}))) if self.mode == "json"
                    else format_line(view))
            if text == self._text:          # a line per change, not per tick
                return
            self._text = text
            self.stream.write(text + "\n")
        else:
            lines = format_lines(view)
            # back to the first line drawn, clear to the end of the screen, redraw
            up = f"\x1b[{self._drawn}F" if self._drawn else ""
            self.stream.write(up + "\x1b[J" + "\n".join(lines) + "\n")
            self._drawn = len(lines)
        self.stream.flush()

    def close(self) -> None:
        """Show the last view received, whatever the interval."""
        if self._last is not None:
            self.show(self._last, force=True)

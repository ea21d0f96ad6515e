"""``socmon watch``: attach to any run, show it live, and record it like ``socmon up``.

:func:`watch` joins the mesh with :func:`agent.run.recorder.watch_run`, shows each
:meth:`agent.run.recorder.Recorder.view` through a :class:`agent.run.live_view.LiveView`, and
at the end summarizes the recording with the functions ``up`` uses
(:func:`agent.run.summary.summarize`) and, given a folder, writes the same run folder
files (``summary.json``, ``mse.csv``, ``mse.json``, ``mse.png``, ``estimates.npz``,
``assignments.json``, and ``events.jsonl`` from the monitor's events heard on the wire).
What the wire does not say (the gains, hence the predicted MSE; the delays the gains were
designed for; the seed) comes from the :class:`WatchConfig`.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from design.plausibility import StateScale

from agent.run.recorder import Recorder, watch_run

__all__ = ["WatchConfig", "WatchResult", "watch", "NoWorld"]


class NoWorld(Exception):
    """Nothing of the run was heard within the timeout."""


@dataclass(frozen=True, eq=False)
class WatchConfig:
    """What a watcher knows of the run besides what it hears."""

    scenario: object
    scenario_arg: str
    net: object                       # broker_free_net.config.NetConfig
    delays: np.ndarray
    delays_spec: str
    G: list | None = None             # the gains of the run: the predicted MSE needs them
    gains_path: Path | None = None
    seed: int | None = None
    steps: int | None = None          # stop once this step is recorded
    step_ms: float | None = None
    out: Path | None = None
    timeout: float = 60.0
    keep_steps: int | None = 100_000  # the recording keeps the newest steps only
    control_public: bytes | None = None   # the run's control key: unsigned control dropped


@dataclass
class WatchResult:
    recording: object
    summary: dict
    steps: list
    mse: np.ndarray
    ended: str                        # steps, world ended, interrupted


def watch(config: WatchConfig, view) -> WatchResult:
    """Record the run of ``config.net`` until it ends; ``view``: a LiveView (or anything
    with ``show(view)`` and ``close()``). Raises :class:`NoWorld` if nothing was heard."""
    from agent.run.folder import write_atomic
    from agent.run.local import RunConfig
    from agent.run.summary import predicted_mse, save_estimates, summarize, write_run_folder

    c = config
    s = c.scenario
    M = s.N + s.standby
    recorder = Recorder(c.net.run, s.n, s.N, M, keep_steps=c.keep_steps,
                        control_public=c.control_public,
                        scale=StateScale(s.A, s.process_noise, s.measurement_noise))
    try:
        ended = watch_run(c.net, recorder, steps=c.steps, timeout=c.timeout,
                          on_view=view.show, interval=getattr(view, "interval", 0.25))
    finally:
        view.close()
    rec = recorder.recording
    if ended == "no world":
        raise NoWorld(f"nothing of run {c.net.run!r} heard within {c.timeout:g} s "
                      f"(connected to {', '.join(c.net.connect) or 'multicast'}): is the "
                      f"world running, and is --run right?")
    # stopped mid-step: end at the last step every live agent published; at the world's
    # end: every step heard, as `up` (a silent agent does not truncate the record)
    last = recorder.last_complete_step(recorder.alive) if ended == "interrupted" \
        else recorder.view()["mse_step"]
    K = c.steps if ended == "steps" else (last if last is not None else -1)
    rho, predicted = predicted_mse(s, c.G, c.delays) if c.G is not None else (None, None)
    if c.out is not None:
        c.out.mkdir(parents=True, exist_ok=True)
        events = c.out / "events.jsonl"
        if rec.monitor_events:
            write_atomic(events, "".join(json.dumps(e) + "\n" for e in rec.monitor_events))
        elif events.exists():       # an earlier run's record, not this one's failures
            events.unlink()
    run_config = RunConfig(
        scenario=s, scenario_arg=c.scenario_arg, G=c.G, gains_path=c.gains_path,
        delays=c.delays, delays_spec=c.delays_spec, steps=K, seed=c.seed, step_ms=c.step_ms,
        deadline_ms=None, out=c.out, monitor=bool(rec.monitor_events), drop=None,
        run_id=c.net.run)
    summary, steps, mse = summarize(run_config, rec, rho, predicted)
    summary.update(watched=True, ended=ended, connect=list(c.net.connect))
    if c.out is not None:
        write_run_folder(c.out, summary, steps, mse, predicted, assigns=rec.assigns)
        active = [a for a in range(1, M + 1) if rec.est[a]]
        save_estimates(c.out / "estimates.npz", steps, rec.truth, rec.est, active, s.n)
        summary["out"] = str(c.out)
    return WatchResult(rec, summary, steps, mse, ended)

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


def watch(config: WatchConfig, view, page=None) -> WatchResult:
    """Record the run of ``config.net`` until it ends; ``view``: a LiveView (or anything
    with ``show(view)`` and ``close()``); ``page``: a :class:`agent.run.web.LivePage` fed
    with the same views (``--web``). Raises :class:`NoWorld` if nothing was heard."""
    from agent.run.folder import write_atomic
    from agent.run.local import RunConfig
    from agent.run.summary import predicted_mse, summarize, write_run_folder

    c = config
    s = c.scenario
    M = s.N + s.standby
    recorder = Recorder(c.net.run, s.n, s.N, M, keep_steps=c.keep_steps,
                        control_public=c.control_public,
                        scale=StateScale(s.A, s.process_noise, s.measurement_noise))
    on_view, interval = view.show, getattr(view, "interval", 0.25)
    live = None
    if page is not None:
        from agent.run.web import TICK_S

        live = page.state_for(s, c.delays, c.G, run_id=c.net.run, gains_path=c.gains_path,
                              step_ms=c.step_ms)

        def on_view(v):              # the terminal's view, and the page's from the same one
            view.show(v)
            live.tick(recorder, set(recorder.alive), force=True, view=v)

        interval = min(interval, TICK_S)
    ended = "interrupted"
    try:
        ended = watch_run(c.net, recorder, steps=c.steps, timeout=c.timeout,
                          on_view=on_view, interval=interval)
    finally:
        view.close()
        if live is not None:
            live.finish(recorder, {"steps": "recorded up to --steps", "world ended":
                                   "the world ended", "world lost":
                                   "the world left without its end", "no world": "no world heard",
                                   "behind": "--steps behind the run"}.get(ended, ended))
    rec = recorder.recording
    if ended == "behind":
        from agent.run.inputs import InputError

        raise InputError(steps_behind_text(c.steps, min(rec.truth)))
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
    if ended == "world lost" and rec.truth:
        summary["warnings"] = summary.get("warnings", []) + [
            f"the world left after step {max(rec.truth)} without its end (killed, paused past "
            "its lease or cut off): the run did not end as planned"]
    if c.out is not None:
        write_run_folder(c.out, summary, steps, mse, predicted, recording=rec, n=s.n)
        summary["out"] = str(c.out)
    return WatchResult(rec, summary, steps, mse, ended)


# ---------------------------------------------------------------------------------
# ``socmon watch``: its flags to a WatchConfig, its live view, what it prints at the end


def control_key(manifest, scenario, gains) -> bytes | None:
    """The run's control public key from its manifest (None without one); the manifest's
    scenario and gains must be the ones given (InputError otherwise)."""
    if manifest is None:
        return None
    from agent.protocol.manifest import ManifestMismatch, check_manifest, public_key
    from agent.run.inputs import InputError

    try:
        return public_key(check_manifest(manifest, scenario, gains, None, None),
                          "control_public_key")
    except ManifestMismatch as exc:
        raise InputError(str(exc)) from None


def watch_config(args, info=None) -> WatchConfig:
    """The :class:`WatchConfig` of ``socmon watch``'s arguments; what they leave out comes
    from ``info`` (the :class:`agent.run.folder.RunInfo` of ``--attach``) when given. Bad
    input is an InputError naming the flag."""
    import math

    from broker_free_net.config import InvalidNetConfig, net_config_from_args
    from design.errors import ScenarioError
    from design.scenario import resolve_delays

    from agent.run.inputs import (
        InputError,
        check_keys_arg,
        check_run_scenario,
        load_gains_arg,
        load_scenario_arg,
    )

    scenario_arg = args.scenario or (info.scenario_arg if info else None)
    if scenario_arg is None:
        raise InputError("SCENARIO: give the run's scenario (or --attach RUN_DIR)")
    scenario = load_scenario_arg(scenario_arg)
    if info is not None and args.scenario:
        check_run_scenario(scenario, info)
    delays_spec = args.delays or (info.delays if info and info.delays else "scenario")
    try:
        delays = resolve_delays(scenario, delays_spec)
    except ScenarioError as exc:
        raise InputError(f"--delays: {exc}") from None
    gains = args.gains or (str(info.gains) if info and info.gains else None)
    G = list(load_gains_arg(gains, scenario).G) if gains else None
    control_public = control_key(args.manifest or (info.manifest if info else None),
                                 scenario, gains)
    for flag, value in (("--interval", args.interval), ("--timeout", args.timeout),
                        ("--step-ms", args.step_ms)):
        if value is not None and not (math.isfinite(value) and value > 0):
            raise InputError(f"{flag}: must be a positive number, got {value}")
    try:
        net = net_config_from_args(args, identity="recorder")
    except InvalidNetConfig as exc:
        raise InputError(exc.as_flag()) from None
    check_keys_arg(net.keys, scenario)
    if not net.connect and not net.multicast:
        raise InputError("--connect: give the endpoint of a process of the run "
                         "(or --attach RUN_DIR, or --multicast on a LAN)")
    return WatchConfig(
        scenario=scenario, scenario_arg=scenario_arg, net=net, delays=delays,
        delays_spec=delays_spec, G=G, gains_path=Path(gains).resolve() if gains else None,
        seed=args.seed if args.seed is not None else (info.seed if info else None),
        steps=args.steps,
        step_ms=args.step_ms if args.step_ms is not None else (info.step_ms if info else None),
        out=Path(args.out) if args.out else None, timeout=args.timeout,
        keep_steps=args.keep_steps, control_public=control_public)


def live_view_for(stream, as_json: bool = False, interval: float | None = None):
    """The :class:`agent.run.live_view.LiveView` of ``socmon watch`` on ``stream``: JSON
    lines with ``as_json``, else redrawn in place on a terminal or plain lines; updated
    every ``interval`` seconds (default 0.25 on a terminal, else 1)."""
    from agent.run.live_view import LiveView

    tty = stream.isatty()
    mode = "json" if as_json else ("tty" if tty else "plain")
    return LiveView(stream, mode, interval if interval is not None else (0.25 if tty else 1.0))


def start_line(config: WatchConfig, out: str | None = None) -> str:
    """What ``socmon watch`` says on stderr as it starts: the run, where it listens, and
    how to end it."""
    return (f"watch: run {config.net.run} via {', '.join(config.net.connect) or 'multicast'}; "
            "Ctrl-C ends the watch" + (f" and writes {out}" if out else ""))


def steps_behind_text(steps: int, step: int) -> str:
    """What ``socmon watch --steps STEPS`` says when it joined the run at ``step``, already
    past STEPS (nothing of the steps it asked for is left to hear).

    >>> steps_behind_text(50, 126)
    '--steps: 50 is behind the run (at step 126 when the watch joined): give a later step, or leave --steps out to watch until the world ends'
    """
    return (f"--steps: {steps} is behind the run (at step {step} when the watch joined): "
            "give a later step, or leave --steps out to watch until the world ends")


def exit_status(result: WatchResult) -> int:
    """``socmon watch``'s exit status: 130 interrupted, 1 when the run's clock never
    started (no step recorded: its world gave up waiting for a process) or its world left
    without its end (killed, paused or cut off), else 0."""
    if result.ended == "interrupted":
        return 130
    return 1 if result.summary.get("steps", -1) < 0 or result.ended == "world lost" else 0


def summary_json(result: WatchResult) -> str:
    """The last line of ``socmon watch --json``: ``{"kind": "summary", ...}``."""
    from agent.run.jsonable import to_jsonable, versioned

    return json.dumps(to_jsonable(versioned({"kind": "summary", **result.summary})))


def summary_lines(result: WatchResult, config: WatchConfig, out: str | None = None) -> list:
    """What ``socmon watch`` prints at the end: how the watch ended and the MSE against its
    prediction for the configuration in force (as ``up`` prints it), the failures, and the
    run folder ``out`` (as the user named it)."""
    from agent.run.summary import failure_lines, prediction_missing, steady_text

    summary = result.summary
    pred = summary.get("mse_steady_exact_in_force")
    how = {"steps": "recorded up to --steps", "world ended": "ended with its world",
           "world lost": "LOST ITS WORLD (its token went without its end: killed, paused "
                         "past its lease or cut off)",
           "interrupted": "watched until interrupted"}.get(result.ended, result.ended)
    if summary.get("steps", -1) < 0:
        why = ("nothing of the run heard" if result.ended == "interrupted" else
               "the world gave up waiting for a process: see its log")
        return [f"{config.scenario.name}: run {config.net.run} {how} before its clock "
                f"started: no step recorded ({why})"] + ([f"run folder: {out}"] if out else [])
    lines = [f"{config.scenario.name}: run {config.net.run} {how}, last step "
             f"{summary['steps']}: mse_steady {steady_text(summary, 'mse_steady')}"
             + (" (no --gains: no prediction)" if summary.get("mse_steady_exact") is None
                else f" (predicted {pred:.4g} for the configuration in force)"
                if pred is not None else f" (predicted {prediction_missing(summary)})")
             + f", drops {summary['drops']}, late {summary['late']}, malformed "
               f"{summary['malformed']}"]
    lines += failure_lines(summary)
    if out:
        lines.append(f"run folder: {out}")
    return lines


__all__ += ["control_key", "watch_config", "live_view_for", "start_line", "steps_behind_text",
            "exit_status", "summary_json", "summary_lines"]

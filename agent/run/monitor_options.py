"""The monitor process that ``socmon monitor``'s flags ask for, checked, and its start.

:func:`monitor_options` turns the flags, with what ``--attach RUN_DIR`` gives for those
left out (:func:`run_flags`), into :class:`MonitorOptions`: the scenario, the gains the
agents run, the delays, the transport, the monitor's thresholds
(:class:`agent.monitor.core.MonitorConfig`) and the signer of its assignments. Every
problem is an :class:`~agent.run.inputs.InputError` (exit 2) naming the flag; the first
one found wins, in this order: SCENARIO, ``--gains`` given, the scenario itself,
``--manifest``, ``--delays``, the gains file, ``--id``, ``--prepare-s``,
``--lead-steps``, the transport flags, ``--step-ms``, the hang timeouts,
``--control-key``. :func:`start_warnings` says what the gains leave at risk and
:func:`start_monitor` runs the process until it ends.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from design.errors import ScenarioError
from design.scenario import resolve_delays

from agent.monitor.core import MonitorConfig
from agent.protocol.manifest import ManifestMismatch, check_manifest
from agent.protocol.timing import DEFAULT as TIMING
from agent.run.inputs import (InputError, check_keys_arg, check_run_scenario, load_gains_arg,
                              load_scenario_arg, timing_arg)

__all__ = ["RunFlags", "run_flags", "MonitorOptions", "monitor_options", "start_warnings",
           "start_monitor"]


@dataclass(frozen=True)
class RunFlags:
    """The flags that name the run a monitor joins: SCENARIO, ``--gains``, ``--delays``,
    ``--seed``, ``--manifest`` and ``--control-key`` (None: not given)."""

    scenario: str | None
    gains: str | None
    delays: str
    seed: int | None
    manifest: str | None
    control_key: str | None


def run_flags(args, info=None) -> RunFlags:
    """The :class:`RunFlags` of ``args``: each flag given, else the run's value from
    ``info`` (the :class:`agent.run.folder.RunInfo` of ``--attach``, None without it);
    ``--delays`` defaults to ``scenario``.

    >>> from pathlib import Path
    >>> from types import SimpleNamespace as NS
    >>> from agent.run.folder import RunInfo
    >>> args = NS(scenario=None, gains=None, delays=None, seed=None, manifest=None,
    ...           control_key="mine.key")
    >>> run_flags(args)
    RunFlags(scenario=None, gains=None, delays='scenario', seed=None, manifest=None, control_key='mine.key')
    >>> info = RunInfo(folder=Path("r"), run="demo", connect="tcp/127.0.0.1:7447",
    ...                processes={}, scenario="paper-14", scenario_arg="paper-14",
    ...                gains=Path("/r/gains.npz"), control_key=Path("/r/control.key"), seed=3)
    >>> run_flags(args, info)
    RunFlags(scenario='paper-14', gains='/r/gains.npz', delays='scenario', seed=3, manifest=None, control_key='mine.key')
    """
    scenario, gains, delays = args.scenario, args.gains, args.delays
    seed, manifest, control_key = args.seed, args.manifest, args.control_key
    if info is not None:
        scenario = scenario or info.scenario_arg
        gains = gains or (str(info.gains) if info.gains else None)
        delays = delays or info.delays
        seed = seed if seed is not None else info.seed
        manifest = manifest or (str(info.manifest) if info.manifest else None)
        control_key = control_key or (str(info.control_key) if info.control_key else None)
    return RunFlags(scenario=scenario, gains=gains, delays=delays or "scenario", seed=seed,
                    manifest=manifest, control_key=control_key)


@dataclass(frozen=True)
class MonitorOptions:
    """What ``socmon monitor`` runs, checked: the monitor ``monitor_id`` of the run of
    ``net`` (a :class:`broker_free_net.config.NetConfig`) for ``scenario`` with the
    agents' gains ``G`` and the link ``delays``; ``events``: the JSON lines file of
    ``--events`` (None: none); ``signer``: the
    :class:`agent.protocol.control_auth.ControlSigner` of ``--control-key`` (None:
    unsigned)."""

    scenario: object
    G: tuple
    delays: object
    net: object
    monitor_id: int
    config: MonitorConfig
    events: str | None
    precompute: bool
    signer: object
    prepare_s: float


def monitor_options(args, info=None, *, net_config_arg, load_signer) -> MonitorOptions:
    """The :class:`MonitorOptions` of ``socmon monitor``'s ``args``, with what ``info``
    (the run of ``--attach``, or None) gives for the run's flags left out.

    ``net_config_arg(args, identity=...)`` reads the transport flags and
    ``load_signer(path)`` the control key: the command line's readers
    (:mod:`agent.cli._common`), passed in since a run does not import the command line.
    InputError naming the first bad flag, in the order of the module's docstring.

    >>> from types import SimpleNamespace as NS
    >>> monitor_options(NS(scenario="paper-14", gains=None, delays=None, seed=None,
    ...                    manifest=None, control_key=None), None, net_config_arg=None,
    ...                 load_signer=None)
    Traceback (most recent call last):
    ...
    agent.run.inputs.InputError: --gains: give the gains file the agents run (or --attach RUN_DIR)
    """
    flags = run_flags(args, info)
    if flags.scenario is None:
        raise InputError("SCENARIO: give the run's scenario (or --attach RUN_DIR)")
    if flags.gains is None:
        raise InputError("--gains: give the gains file the agents run (or --attach "
                         "RUN_DIR)")
    scenario = load_scenario_arg(flags.scenario)
    if info is not None and args.scenario:
        check_run_scenario(scenario, info)
    if flags.manifest:
        try:
            check_manifest(flags.manifest, scenario, flags.gains, flags.seed, flags.delays)
        except ManifestMismatch as exc:
            raise InputError(str(exc)) from None
    try:
        delays = resolve_delays(scenario, flags.delays)
    except ScenarioError as exc:
        raise InputError(f"--delays: {exc}") from None
    G = load_gains_arg(flags.gains, scenario, force=args.force_gains).G
    if args.id < 1:
        raise InputError(f"--id: must be >= 1, got {args.id}")
    if not (math.isfinite(args.prepare_s) and 0 <= args.prepare_s < TIMING.start_timeout_s):
        raise InputError(f"--prepare-s: must be in [0, {TIMING.start_timeout_s:g}) "
                         f"(the world's start timeout), got {args.prepare_s}")
    if args.lead_steps < 1:
        raise InputError(f"--lead-steps: must be >= 1, got {args.lead_steps}")
    net = net_config_arg(args, identity="monitor")
    check_keys_arg(net.keys, scenario)
    step_ms = args.step_ms if args.step_ms is not None else scenario.step_ms
    if not (math.isfinite(step_ms) and step_ms > 0):
        raise InputError(f"--step-ms: must be > 0, got {step_ms}")
    timing = timing_arg(step_s=step_ms / 1000.0, lead_steps=args.lead_steps,
                        hang_timeout_s=args.hang_timeout,
                        hang_timeout_max_s=args.hang_timeout_max)
    config = MonitorConfig.from_timing(timing, lead_steps=args.lead_steps,
                                       step_s=step_ms / 1000.0,
                                       lease_s=net.lease_ms / 1000.0)
    signer = load_signer(flags.control_key) if flags.control_key else None
    return MonitorOptions(scenario=scenario, G=tuple(G), delays=delays, net=net,
                          monitor_id=args.id, config=config, events=args.events,
                          precompute=not args.no_precompute, signer=signer,
                          prepare_s=args.prepare_s)


def start_warnings(options: MonitorOptions) -> list:
    """The lines ``socmon monitor`` prints on stderr before it starts: a warning for each
    single failure whose gap loop the gains leave unstable
    (:func:`design.gap.gap_warnings`)."""
    from design.gap import gap_warnings

    return [f"monitor {options.monitor_id}: warning: {line}"
            for line in gap_warnings(options.scenario, list(options.G), options.delays)]


def start_monitor(options: MonitorOptions) -> int:
    """Run the monitor process of ``options`` until it is stopped
    (:func:`agent.monitor.process.run_monitor`); its exit status."""
    from agent.monitor.process import run_monitor

    return run_monitor(options.scenario, list(options.G), options.delays, options.net,
                       monitor_id=options.monitor_id, config=options.config,
                       events_out=options.events, precompute=options.precompute,
                       signer=options.signer, prepare_s=options.prepare_s)

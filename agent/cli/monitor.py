"""``socmon monitor SCENARIO --run RUN``: detect failed agents and hand their roles over."""

from __future__ import annotations

from agent.protocol.timing import DEFAULT as TIMING

HELP = "run the monitor: detect failed agents and reassign their roles to equivalent agents"


def add_arguments(parser) -> None:
    from broker_free_net.config import add_net_arguments

    from agent.cli._common import add_attach_argument, add_force_gains_argument, add_manifest_argument

    parser.add_argument("scenario", nargs="?",
                        help="scenario TOML file or built-in name (default with --attach: "
                             "the run's)")
    add_attach_argument(parser, takes=", and the scenario, gains, delays, seed, manifest and "
                                      "control key of the run (use another --id than the "
                                      "run's monitor, 1)")
    parser.add_argument("--gains", metavar="FILE",
                        help="the gains file the agents run (.npz; required unless --attach)")
    add_force_gains_argument(parser)
    parser.add_argument("--delays", default=None,
                        help="link delays of the run: scenario, none or uniform:T (default "
                             "scenario, or the run's with --attach); new gains are certified "
                             "for them")
    parser.add_argument("--seed", type=int, default=None,
                        help="the run's seed (only checked against --manifest)")
    parser.add_argument("--id", type=int, default=1,
                        help="monitor id; with several monitors the smallest live id acts "
                             "(default 1)")
    parser.add_argument("--hang-timeout", type=float, default=TIMING.hang_timeout_s,
                        metavar="S",
                        help="no progress of an agent for S seconds while the others advance "
                             f"is a hang (default {TIMING.hang_timeout_s:g}; lower is faster "
                             "and risks convicting a slow agent; above twice the status "
                             f"period {TIMING.status_s:g} s)")
    parser.add_argument("--hang-timeout-max", type=float, default=TIMING.hang_timeout_max_s,
                        metavar="S",
                        help="the hang timeout grows with the statuses' observed pace up to S "
                             f"seconds (default {TIMING.hang_timeout_max_s:g}; equal to "
                             "--hang-timeout keeps it fixed; docs/monitor.md)")
    parser.add_argument("--lead-steps", type=int, default=10,
                        help="activate a reassignment this many steps after the newest step "
                             "reported (default 10)")
    parser.add_argument("--step-ms", type=float, default=None,
                        help="the run's step period (default: the scenario's step_ms)")
    parser.add_argument("--events", metavar="FILE",
                        help="append every verdict and reassignment to FILE as JSON lines")
    parser.add_argument("--control-key", metavar="FILE",
                        help="the run's control key (32 raw bytes; socmon up writes "
                             "RUN_FOLDER/control.key): every assignment and roster is signed")
    parser.add_argument("--no-precompute", action="store_true",
                        help="do not precompute the single failures at start-up")
    parser.add_argument("--prepare-s", type=float, default=TIMING.monitor_prepare_s,
                        metavar="S",
                        help="monitor 1 joins the run once it has the gains of every single "
                             "failure, waiting at most S seconds (default "
                             f"{TIMING.monitor_prepare_s:g}; 0 joins at once, as a monitor "
                             "started again in a run in progress should)")
    add_manifest_argument(parser)
    add_net_arguments(parser)


def run(args) -> int:
    from agent.cli._common import CommandError, run_command, timing_arg

    def body():
        import math

        from design.errors import ScenarioError
        from design.scenario import resolve_delays

        from agent.monitor.core import MonitorConfig
        from agent.monitor.process import run_monitor
        from agent.cli._common import attach_run, load_gains_arg, load_scenario_arg, net_config_arg

        info = attach_run(args)
        if info is not None:
            args.scenario = args.scenario or info.scenario_arg
            args.gains = args.gains or (str(info.gains) if info.gains else None)
            args.delays = args.delays or info.delays
            args.seed = args.seed if args.seed is not None else info.seed
            args.manifest = args.manifest or (str(info.manifest) if info.manifest else None)
            args.control_key = args.control_key or (str(info.control_key)
                                                    if info.control_key else None)
        args.delays = args.delays or "scenario"
        if args.scenario is None:
            raise CommandError("SCENARIO: give the run's scenario (or --attach RUN_DIR)")
        if args.gains is None:
            raise CommandError("--gains: give the gains file the agents run (or --attach "
                               "RUN_DIR)")
        scenario = load_scenario_arg(args.scenario)
        if args.manifest:
            from agent.protocol.manifest import ManifestMismatch, check_manifest

            try:
                check_manifest(args.manifest, scenario, args.gains, args.seed, args.delays)
            except ManifestMismatch as exc:
                raise CommandError(str(exc)) from None
        try:
            delays = resolve_delays(scenario, args.delays)
        except ScenarioError as exc:
            raise CommandError(f"--delays: {exc}") from None
        G = load_gains_arg(args.gains, scenario, force=args.force_gains).G
        if args.id < 1:
            raise CommandError(f"--id: must be >= 1, got {args.id}")
        if not (math.isfinite(args.prepare_s) and 0 <= args.prepare_s
                < TIMING.start_timeout_s):
            raise CommandError(f"--prepare-s: must be in [0, {TIMING.start_timeout_s:g}) "
                               f"(the world's start timeout), got {args.prepare_s}")
        if args.lead_steps < 1:
            raise CommandError(f"--lead-steps: must be >= 1, got {args.lead_steps}")
        net = net_config_arg(args, identity="monitor")
        step_ms = args.step_ms if args.step_ms is not None else scenario.step_ms
        if not (math.isfinite(step_ms) and step_ms > 0):
            raise CommandError(f"--step-ms: must be > 0, got {step_ms}")
        timing = timing_arg(step_s=step_ms / 1000.0, lead_steps=args.lead_steps,
                            hang_timeout_s=args.hang_timeout,
                            hang_timeout_max_s=args.hang_timeout_max)
        config = MonitorConfig.from_timing(timing, lead_steps=args.lead_steps,
                                           step_s=step_ms / 1000.0)
        from agent.cli._common import load_signer

        signer = load_signer(args.control_key) if args.control_key else None
        import sys

        from design.gap import gap_warnings

        for line in gap_warnings(scenario, list(G), delays):
            print(f"monitor {args.id}: warning: {line}", file=sys.stderr, flush=True)
        return run_monitor(scenario, list(G), delays, net, monitor_id=args.id, config=config,
                           events_out=args.events, precompute=not args.no_precompute,
                           signer=signer, prepare_s=args.prepare_s)

    return run_command(body)

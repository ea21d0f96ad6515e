"""``socmon world SCENARIO``: the social system and the clock of a live run."""

from __future__ import annotations

HELP = "run the world: simulate the social system and publish sensor readings (the clock)"


def add_arguments(parser) -> None:
    from broker_free_net.config import add_net_arguments

    from agent.cli import _common as c

    c.add_scenario_argument(parser)
    c.add_seed_argument(parser)
    parser.add_argument("--steps", type=c.int_flag(lo=0), default=None,
                        help="last step to publish (default: run until stopped)")
    c.add_step_ms_argument(parser)
    parser.add_argument("--wait-agents", default=None, metavar="IDS",
                        help="agent ids to wait for before the clock starts, e.g. 1,2,3 "
                             "(default: every active and standby agent of the scenario)")
    parser.add_argument("--wait-monitor", type=c.int_flag(lo=1), default=None, metavar="ID",
                        help="also wait for monitor ID before the clock starts (it joins "
                             "once its gains for every single failure are ready, so that a "
                             "failure soon after the start is answered at once)")
    c.add_start_timeout_argument(parser, "the agents")
    c.add_manifest_argument(parser)
    add_net_arguments(parser)


def run(args) -> int:
    from agent.cli._common import CommandError, run_command

    def body():

        from agent.world.process import run_world
        from agent.cli._common import (check_keys_arg, check_run_flags, load_scenario_arg,
                                       net_config_arg, parse_int_list)

        check_run_flags(args)
        scenario = load_scenario_arg(args.scenario)
        if args.manifest:
            from agent.protocol.manifest import ManifestMismatch, check_manifest

            try:
                check_manifest(args.manifest, scenario, None, args.seed, None)
            except ManifestMismatch as exc:
                raise CommandError(str(exc)) from None
        if args.step_ms is not None and not args.step_ms > 0:
            raise CommandError(f"--step-ms: must be > 0, got {args.step_ms}")
        M = scenario.N + scenario.standby
        wait = None
        if args.wait_agents is not None:
            wait = parse_int_list(args.wait_agents, "--wait-agents", lo=1, hi=M,
                                  item="agent", allow_empty=True,
                                  what="expected comma-separated agent ids",
                                  out_of_range="no agent {value} (agents are 1..{hi})")
        net = net_config_arg(args, identity="world")
        check_keys_arg(net.keys, scenario)
        return run_world(scenario, net, seed=args.seed, steps=args.steps, step_ms=args.step_ms,
                         wait_agents=wait, start_timeout=args.start_timeout,
                         wait_monitor=args.wait_monitor)

    return run_command(body)

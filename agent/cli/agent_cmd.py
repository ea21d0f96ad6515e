"""``socmon agent SCENARIO --id I``: one agent process of a live run.

The flags checked together, the manifest's keys, the agent's configuration and its
start: :mod:`agent.run.agent_options`. Exit status: 0 the world left or the agent was
stopped, 1 the world fell silent without its end, 2 bad input (the message names the
flag).
"""

from __future__ import annotations

from agent.cli._common import net_config_arg, parse_int, run_command

HELP = "run one agent: the shared estimator step every step, over zenoh"


def add_arguments(parser) -> None:
    from broker_free_net.config import add_net_arguments

    from agent.cli import _common as c

    c.add_scenario_argument(parser)
    parser.add_argument("--id", type=c.int_flag(lo=1), required=True,
                        help="agent id (1..N active, N+1.. standby agents of the scenario)")
    c.add_designed_gains_arguments(parser, " (every agent designs the same gain)")
    c.add_seed_argument(parser, help="run seed (same as the world's)")
    c.add_delays_argument(parser, "link delays injected at start (receiver side)")
    c.add_deadline_argument(parser)
    c.add_drop_argument(parser)
    parser.add_argument("--lie", default=None, metavar="STEP:SIZE",
                        help="scripted misbehaviour: from STEP on, publish estimates SIZE "
                             "measurement-noise std-devs off on every component, the agent's "
                             "own estimate staying honest (socmon up --fault lie uses it)")
    parser.add_argument("--sensor-fault", action="append", default=[],
                        metavar="KIND:STEP:SIZE",
                        help="scripted sensor fault (repeatable): from STEP on, bias (SIZE "
                             "noise std-devs added to every reading), drift (SIZE std-devs "
                             "after 100 steps, growing on) or noise (the sensor noise "
                             "times SIZE) (socmon up --fault bias/drift/noise uses it)")
    parser.add_argument("--crash-at", type=c.int_flag(lo=1), default=None, metavar="STEP",
                        help="scripted crash: publish step STEP-1, then SIGKILL itself "
                             "(reproducible failures; socmon up --kill uses it)")
    c.add_manifest_argument(parser)
    add_net_arguments(parser)


def run(args) -> int:
    return run_command(lambda: _run(args))


def _run(args) -> int:
    from agent.run.agent_options import agent_options, start_agent

    return start_agent(agent_options(args, net_config_arg=net_config_arg, parse_int=parse_int))

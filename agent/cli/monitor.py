"""``socmon monitor SCENARIO --run RUN``: detect failed agents and hand their roles over.

The flags checked together (with what ``--attach RUN_DIR`` gives), the monitor's
configuration and its start: :mod:`agent.run.monitor_options`. Exit status: 0 stopped
or the run over, 2 bad input (the message names the flag).
"""

from __future__ import annotations

import sys

from agent.cli._common import attach_run, load_signer, net_config_arg, run_command
from agent.protocol.timing import DEFAULT as TIMING

HELP = "run the monitor: detect failed agents and reassign their roles to equivalent agents"


def add_arguments(parser) -> None:
    from broker_free_net.config import add_net_arguments

    from agent.cli import _common as c

    c.add_scenario_argument(parser, attach=True)
    c.add_attach_argument(parser, takes=", and the scenario, gains, delays, seed, manifest and "
                                        "control key of the run (use another --id than the "
                                        "run's monitor, 1)")
    parser.add_argument("--gains", metavar="FILE",
                        help="the gains file the agents run (.npz; required unless --attach)")
    c.add_force_gains_argument(parser)
    c.add_delays_argument(parser, "link delays of the run, for which new gains are certified",
                          attach=True)
    c.add_seed_argument(parser, default=None, help="the run's seed (only checked against "
                                                   "--manifest)")
    parser.add_argument("--id", type=c.int_flag(lo=1), default=1,
                        help="monitor id; with several monitors the smallest live id acts "
                             "(default 1)")
    c.add_hang_timeout_arguments(parser)
    parser.add_argument("--lead-steps", type=c.int_flag(lo=1), default=10,
                        help="activate a reassignment this many steps after the newest step "
                             "reported (default 10)")
    c.add_step_ms_argument(parser, "the run's period of one step in ms")
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
    c.add_manifest_argument(parser)
    add_net_arguments(parser)


def run(args) -> int:
    return run_command(lambda: _run(args))


def _run(args) -> int:
    from agent.run.monitor_options import monitor_options, start_monitor, start_warnings

    options = monitor_options(args, attach_run(args), net_config_arg=net_config_arg,
                              load_signer=load_signer)
    for line in start_warnings(options):
        print(line, file=sys.stderr, flush=True)
    return start_monitor(options)

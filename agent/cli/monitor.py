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
    return run_command(lambda: _run(args))


def _run(args) -> int:
    from agent.run.monitor_options import monitor_options, start_monitor, start_warnings

    options = monitor_options(args, attach_run(args), net_config_arg=net_config_arg,
                              load_signer=load_signer)
    for line in start_warnings(options):
        print(line, file=sys.stderr, flush=True)
    return start_monitor(options)

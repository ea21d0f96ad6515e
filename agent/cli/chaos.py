"""``socmon chaos SCENARIO --seed S``: a live run under a random fault schedule, checked;
``--simulated A:B``: seeds A..B-1 under simulated time (:mod:`agent.run.simulated`).

The flags checked together, the schedule, the run and its invariants:
:func:`agent.run.chaos.live_chaos` and :func:`agent.run.simulated.simulated_chaos`;
the seeds of ``--simulated`` and the report printed: :mod:`agent.run.chaos_report`.
Exit status: 0 no violation, 1 a violation or a failed run, 2 bad input.
"""

from __future__ import annotations

import sys

from agent.cli._common import parse_int, run_command

HELP = "run live under a random fault schedule drawn from a seed and check the invariants"


def add_arguments(parser) -> None:
    from agent.cli import _common as c

    c.add_scenario_argument(parser)
    c.add_seed_argument(parser, help="seed of the fault schedule and of the run (default 0)")
    parser.add_argument("--duration", type=c.int_flag(lo=100), default=1000, metavar="STEPS",
                        help="steps to run (default 1000)")
    parser.add_argument("--faults", default="kill,stop,hang,sensor,monitor,partition,delay,drop",
                        help="fault kinds to draw from (default: kill, stop, hang, "
                             "sensor, monitor, partition, delay, drop; lie and bias may be "
                             "added: an agent that lies, or whose sensor is biased)")
    parser.add_argument("--rate", type=float, default=3.0,
                        help="faults per 1000 steps (default 3; at least 160 steps apart)")
    c.add_designed_gains_arguments(parser)
    c.add_delays_argument(parser)
    c.add_step_ms_argument(parser)
    c.add_hang_timeout_arguments(parser, with_max=False)
    c.add_run_folder_arguments(parser, "runs/chaos-<scenario>-s<seed>-<time>")
    parser.add_argument("--simulated", metavar="A:B",
                        help="no processes: run seeds A..B-1 under simulated time "
                             "(agent.run.simulated: world, agents and monitors in this process) "
                             "and report them together; --faults may add slow, monitorstop "
                             "and monitorsgone, without linkdown or worldstop")
    c.add_json_argument(parser, "print the report as JSON")
    c.add_quiet_argument(parser)


def run(args) -> int:
    return run_command(lambda: _chaos(args))


def _chaos(args) -> int:
    from agent.run.chaos import live_chaos
    from agent.run.local import live_view
    from agent.run.web import live_state_factory
    from agent.run.chaos_report import (NO_FAULT_WARNING, live_report_text, seed_range,
                                        simulated_report_text)
    from agent.run.simulated import simulated_chaos
    from agent.run.terminal import say_on_stderr

    if args.simulated:
        seeds = seed_range(args.simulated, parse_int)
        report = simulated_chaos(args, seeds)
        print(simulated_report_text(report, seeds, args.rate, as_json=args.json))
        return 1 if report["violations"] else 0
    with live_view(live_state_factory(None)):     # verdicts and reassignments, as heard
        report, status = live_chaos(args, say_on_stderr("chaos", args.quiet))
    if not report["faults"]:
        print(NO_FAULT_WARNING, file=sys.stderr)
    print(live_report_text(report, as_json=args.json))
    if report["error"]:
        print(f"socmon chaos: {report['error']}", file=sys.stderr)
    return status

"""``socmon analyze SCENARIO [--json]``: structure, observability, detectability, tolerance.

The record and its text: :mod:`agent.run.design_reports`. Exit status: 0, or 1 when the
agents' network is not detectable (no gain helps), 2 for bad input.
"""

from __future__ import annotations

import sys

from agent.cli._common import (
    EXIT_NEGATIVE,
    EXIT_OK,
    add_force_gains_argument,
    add_json_argument,
    add_scenario_argument,
    int_flag,
    load_scenario_arg,
    print_json,
    run_command,
)
from agent.run.design_reports import analysis_report, format_analysis

HELP = "structural and numerical analysis of a scenario (SCCs, observability, failure tolerance)"


def add_arguments(parser) -> None:
    add_scenario_argument(parser)
    add_json_argument(parser)
    parser.add_argument("--max-subsets", type=int_flag(lo=1), default=None, metavar="K",
                        help="bound on the failure sets examined for the failure tolerance "
                             "(default 20000; past it the tolerance is a lower bound)")
    parser.add_argument("--gains", default=None, metavar="FILE",
                        help="also report, for these gains, the loop each single failure "
                             "leaves until the switch (exact radius and steady MSE with the "
                             "scenario's delays, own-loop radii), as certify does")
    add_force_gains_argument(parser)


def run(args) -> int:
    return run_command(lambda: _run(args))


def _run(args) -> int:
    scenario = load_scenario_arg(args.scenario)
    data = analysis_report(scenario, max_subsets=args.max_subsets, gains_file=args.gains,
                           force_gains=args.force_gains)
    if args.json:
        print_json(data)
    else:
        print(format_analysis(data))
    if not data["distributed_detectable"]:      # a negative result: no gain can help
        print("socmon analyze: the agents' network is not detectable: no gain makes the "
              "distributed estimator's error bounded", file=sys.stderr)
        return EXIT_NEGATIVE
    return EXIT_OK

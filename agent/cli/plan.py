"""``socmon plan SCENARIO --fail 1,2 [--json]``: recovery plan after agent failures.

The policy (which node replaces a lost one, who measures it, how W is rebuilt, which
links are added) is documented in :mod:`design.recovery`; the record and its text:
:mod:`agent.run.design_reports`. Exit status: 0 when the new configuration is recoverable
(an agent left, every parent SCC measured, network strongly connected, links added if
allowed) and its distributed pair (W' (x) A, D_H') is detectable, so that a stabilising
gain exists; 1 when not; 2 for bad input. ``--write-scenario FILE`` writes the new
configuration as a scenario TOML, ready for ``socmon design`` / ``certify``.
"""

from __future__ import annotations

from design.reports import is_recovered

from agent.cli._common import (EXIT_NEGATIVE, EXIT_OK, add_json_argument, add_scenario_argument,
                               load_scenario_arg, parse_agent_list, print_json, run_command)
from agent.run.design_reports import format_plan, plan_report

HELP = "recovery plan after agent failures: replacements, new W, added links, observability"


def add_arguments(parser) -> None:
    add_scenario_argument(parser)
    parser.add_argument("--fail", required=True, metavar="IDS",
                        help="failed agent ids, comma-separated (agents are 1..N)")
    parser.add_argument("--no-new-links", action="store_true",
                        help="do not add links even if the agent network falls apart")
    parser.add_argument("--write-scenario", metavar="FILE", default=None,
                        help="write the recovered configuration as a scenario TOML file")
    add_json_argument(parser)


def run(args) -> int:
    return run_command(lambda: _run(args))


def _run(args) -> int:
    scenario = load_scenario_arg(args.scenario)
    failed = parse_agent_list(args.fail, scenario, flag="--fail")
    data = plan_report(scenario, failed, add_links=not args.no_new_links,
                       write_scenario=args.write_scenario)
    if args.json:
        print_json(data)
    else:
        print(format_plan(data))
    return EXIT_OK if is_recovered(data) else EXIT_NEGATIVE

"""``socmon certify SCENARIO --gains FILE [--taus 0,3,7,15] [--json]``: exact certificates.

What each figure means is documented in :mod:`design.certificates`; the record and its
text: :mod:`agent.run.design_reports`. Exit status: 0 when the gain is stable with the
scenario's own delays (exact radius < 1), 1 when it is not, 2 for bad input (scenario,
gains file, gains that do not fit, bad ``--taus``).
"""

from __future__ import annotations

from design.certificates import DEFAULT_TAU_CAP, certify
from design.scenario import MAX_DELAY

from agent.cli._common import (
    EXIT_NEGATIVE,
    EXIT_OK,
    add_gains_argument,
    add_json_argument,
    add_scenario_argument,
    int_flag,
    load_gains_arg,
    load_scenario_arg,
    parse_int_list,
    print_json,
    run_command,
)
from agent.cli._progress import ProgressLine
from agent.run.design_reports import certificate_report, format_certificates

HELP = "exact stability radius, Theorem 1 criterion, paper formula, steady MSE and Phi of a gain"


def add_arguments(parser) -> None:
    add_scenario_argument(parser)
    add_gains_argument(parser)
    parser.add_argument("--taus", default="0,3,7,15", metavar="T1,T2,...",
                        help="uniform inter-agent delays to certify (default 0,3,7,15)")
    parser.add_argument("--tau-cap", type=int_flag(lo=0), default=None, metavar="T",
                        help="largest tau examined in the Theorem 1 tau_star search (default 100)")
    add_json_argument(parser)


def run(args) -> int:
    return run_command(lambda: _run(args))


def _run(args) -> int:
    taus = parse_int_list(args.taus, "--taus", lo=0, hi=MAX_DELAY, item="delay",
                          what="expected comma-separated non-negative integers",
                          out_of_range="{value} is above the largest delay, {hi}")
    cap = DEFAULT_TAU_CAP if args.tau_cap is None else args.tau_cap
    scenario = load_scenario_arg(args.scenario)
    gains = load_gains_arg(args.gains, scenario, force=args.force_gains)
    with ProgressLine("certify", enabled=not args.json, delay=0) as line:
        certified = certify(scenario, gains.G, taus=taus, tau_cap=cap, progress=line.update)
    record = certificate_report(certified, scenario, gains, args.gains)
    if args.json:
        print_json(record)
    else:
        print(format_certificates(record))
    return EXIT_OK if record["stable"] else EXIT_NEGATIVE

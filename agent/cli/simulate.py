"""``socmon simulate SCENARIO --gains FILE ...``: Monte-Carlo MSE of the distributed estimator.

Runs :mod:`agent.run.simulate` (timeline and conventions in docs/simulation.md). Exit
status: 0 when the run stays bounded, 1 when it diverged (or ``--recover`` finds no
recovery / no stabilising gain for it), 2 for bad input (named in the message).
"""

from __future__ import annotations

from agent.cli._common import (add_delays_argument, add_gains_argument, add_json_argument,
                               add_scenario_argument, add_seed_argument, int_flag,
                               load_gains_arg, load_scenario_arg, parse_drop, parse_fail,
                               print_json, resolve_delays_arg, run_command)
from agent.cli._progress import ProgressBar, ProgressLine

HELP = "Monte-Carlo simulation: mean-squared error over time, with delays, drops, failures"


def add_arguments(parser) -> None:
    add_scenario_argument(parser)
    add_gains_argument(parser)
    parser.add_argument("--trials", type=int_flag(lo=1), default=20, metavar="T",
                        help="Monte-Carlo trials (default 20)")
    parser.add_argument("--steps", type=int_flag(lo=1), default=300, metavar="K",
                        help="time steps (default 300)")
    add_seed_argument(parser, help="seed of every random number (default 0)")
    add_delays_argument(parser, "link delays", metavar="SPEC")
    parser.add_argument("--drop", default="0", metavar="P",
                        help="probability that one message is lost (default 0)")
    parser.add_argument("--fail", default=None, metavar="STEP:AGENTS",
                        help="agents (1-based ids, comma-separated) fail at STEP, e.g. 150:1,2")
    parser.add_argument("--recover", action="store_true",
                        help="at the failure step, switch to the recovery plan with gains "
                             "designed for the new configuration (warm started from --gains; "
                             "the design stops when it has converged)")
    parser.add_argument("--time-limit", type=float, default=None, metavar="SECONDS",
                        help="--recover: cap on the recovery gain design; the best gain "
                             "found is kept (default: none, the design stops when converged)")
    parser.add_argument("--plot", default=None, metavar="OUT.png",
                        help="write the MSE figure (log scale, 10-90 percentile band)")
    add_json_argument(parser)


def run(args) -> int:
    return run_command(lambda: _run(args))


def _run(args) -> int:
    from agent.cli._plot import figure_path, plot_mse
    from agent.run.simulate import (design_recovery, format_text, run_simulation,
                                    simulate_options, write_figure)

    plot = figure_path(args.plot) if args.plot else None
    scenario = load_scenario_arg(args.scenario)
    gains = load_gains_arg(args.gains, scenario, force=args.force_gains)
    delays = resolve_delays_arg(scenario, args.delays)
    fail = parse_fail(args.fail, scenario, args.steps) if args.fail is not None else None
    o = simulate_options(scenario, gains, args.gains, trials=args.trials, steps=args.steps,
                         seed=args.seed, drop=parse_drop(args.drop), delays=delays,
                         delays_spec=args.delays, fail=fail, recover=args.recover,
                         time_limit=args.time_limit)
    recovery = (None, None)
    if o.recover:
        with ProgressLine("simulate --recover", enabled=not args.json) as line:
            line.context = "gains for the recovered network"
            recovery = design_recovery(o, progress=line.design)
    bar = ProgressBar("simulate")
    bar.enabled = bar.enabled and not args.json
    try:
        report = run_simulation(o, recovery, progress=bar)
    finally:
        bar.close()
    if plot:
        write_figure(plot, o, report, plot_mse)
    if args.json:
        print_json(report.record)
    else:
        print(format_text(report.record))
    return report.status

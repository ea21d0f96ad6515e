"""``socmon design``: design the agents' gains and write the gains file.

The flags checked together, the design, the file written and the text:
:mod:`agent.run.design_reports`. Exit status: 0 a stabilising gain was written; 1 no
stabilising gain was found (no file unless ``--force``) or the conic solver failed; 2 bad
input (an existing ``--out`` file without ``--overwrite`` included, refused before the
design), or the pair is not observable (the message names the parent SCC without a
sensor).
"""

from __future__ import annotations

import sys

from agent.cli._common import (EXIT_NEGATIVE, EXIT_OK, add_delays_argument, add_json_argument,
                               add_scenario_argument, add_seed_argument, int_flag,
                               load_scenario_arg, print_json, run_command)
from agent.cli._progress import ProgressLine
from agent.run.design_reports import (design_for, design_notes, design_report, design_request,
                                      format_design)

HELP = "design the agents' gains (the paper's LMI method or the delay-aware default)"


def add_arguments(parser) -> None:
    add_scenario_argument(parser)
    parser.add_argument("--method", choices=("default", "ccl"), default="default",
                        help="default: first-order design on the exact delayed loop; "
                             "ccl: the paper's LMI algorithm (delay-free)")
    add_delays_argument(parser, "delay matrix to design for and certify against",
                        metavar="scenario|none|uniform:T")
    parser.add_argument("--objective", choices=("rho", "mse"), default=None,
                        help="minimise the exact steady MSE or spectral radius (default: mse "
                             "with --method default, as `up`; rho with --method ccl or --target)")
    add_seed_argument(parser, help="seed of the extra starts (default 0)")
    parser.add_argument("--solver", type=str.upper, choices=("CLARABEL", "SCS"), default=None,
                        help="conic solver for --method ccl (default CLARABEL)")
    parser.add_argument("--max-iter", type=int_flag(lo=0), default=None, metavar="N",
                        help="iterations: BFGS per start and stage (default 200) or "
                             "cone-complementarity iterations (default 50)")
    parser.add_argument("--starts", type=int_flag(lo=1), default=None, metavar="K",
                        help="--method default: number of starts (default 3 for --objective "
                             "rho, 1 for mse)")
    parser.add_argument("--time-limit", type=float, default=None, metavar="SECONDS",
                        help="keep the best gain found after this long (default: 60 s for "
                             "--objective rho, slow with long delays; none for mse, whose "
                             "result then does not depend on the machine's speed)")
    parser.add_argument("--window", type=int_flag(lo=1), default=None, metavar="N",
                        help="--method default: a stage stops when its objective fell by "
                             "less than --rel-tol over the last N iterations (default 20)")
    parser.add_argument("--rel-tol", type=float, default=None, metavar="X",
                        help="--method default: relative progress over --window below which "
                             "a stage stops (default 1e-3)")
    parser.add_argument("--target", type=float, default=None, metavar="RHO",
                        help="--method default, --objective rho: stop once rho < RHO")
    parser.add_argument("--no-gaps", action="store_true",
                        help="--method default: design for the nominal loop alone, not also "
                             "for the loop each single failure leaves until the switch")
    parser.add_argument("--keep-iterating", action="store_true",
                        help="--method ccl: go on after rho < 1 to lower rho")
    parser.add_argument("--out", required=True, metavar="FILE",
                        help="gains file to write (.npz); an existing file is refused")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace an existing --out file")
    add_json_argument(parser)
    parser.add_argument("--force", action="store_true",
                        help="write the gains file even when the design is not stabilising")


def run(args) -> int:
    return run_command(lambda: _run(args))


def _run(args) -> int:
    request = design_request(load_scenario_arg(args.scenario), args)
    with ProgressLine("design", enabled=not args.json) as line:
        result = design_for(request, progress=line.design)
    record = design_report(request, result)     # writes the gains file if stable or --force
    if args.json:
        print_json(record)
    else:
        print(format_design(record))
    for note in design_notes(record, warnings=not args.json):
        print(f"socmon: {note}", file=sys.stderr)
    return EXIT_OK if record["stable"] else EXIT_NEGATIVE

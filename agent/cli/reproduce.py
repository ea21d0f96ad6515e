"""``socmon reproduce [--sampson PATH] --out DIR``: the paper's Section 5, recomputed.

Rho tables, MSE figures (with and without the failure of the agents measuring 7 and 9)
and steady MSE for paper-14 and, given its edge list, Sampson's monastery, with
``report.md`` and ``results.json``: what is computed and written is described in
:mod:`agent.run.reproduce`. Exit status: 0 done, 1 some configuration had no
stabilising gain or a run diverged, 2 bad input.
"""

from __future__ import annotations

from agent.cli._common import EXIT_NEGATIVE, EXIT_OK, parse_int, run_command
from agent.cli._plot import plot_mse
from agent.cli._progress import ProgressLine
from agent.run.reproduce import reproduce_options, run_section5, write_reproduction

HELP = "regenerate the paper's Section 5 (rho tables, MSE figures, steady MSE) with a report"


def add_arguments(parser) -> None:
    parser.add_argument("--out", required=True, metavar="DIR",
                        help="output folder (created): report.md, PNG figures, results.json")
    parser.add_argument("--sampson", default=None, metavar="PATH",
                        help="Sampson edge list to reproduce Section 5.2 (the data set's CSV: row "
                             "s,t: s named t, so t influences s)")
    parser.add_argument("--steps", default="300", metavar="K",
                        help="time steps per simulation (default 300)")
    parser.add_argument("--seed", default="0", metavar="S", help="seed (default 0)")
    parser.add_argument("--trials", default=None, metavar="T",
                        help="Monte-Carlo trials (default: the paper's, 20 and 50)")
    parser.add_argument("--objective", default="mse", choices=("rho", "mse"),
                        help="gain design objective: mse (smallest exact steady MSE, "
                             "certified stable; default: the MSE figures compare errors) or "
                             "rho (smallest exact radius, the paper's design goal; slower, "
                             "and its MSE is not designed for)")
    parser.add_argument("--time-limit", default=None, metavar="SECONDS",
                        help="cap on each gain design, the best gain so far kept (default: "
                             "none; each design stops when converged: relative progress "
                             "< 1e-3 over 20 iterations, or 200 iterations)")


def run(args) -> int:
    return run_command(lambda: _run(args))


def _run(args) -> int:
    steps = parse_int(args.steps, "--steps", lo=1)
    seed = parse_int(args.seed, "--seed", lo=0)
    trials = parse_int(args.trials, "--trials", lo=1) if args.trials is not None else None
    options = reproduce_options(args.out, steps=steps, seed=seed, trials=trials,
                                objective=args.objective, time_limit=args.time_limit,
                                sampson=args.sampson)
    with ProgressLine("reproduce") as line:     # a terminal only: nothing in pipes and files
        results = run_section5(options, log=line.note, progress=line.design,
                               sim_progress=line.simulation)
    report = write_reproduction(options.out, results, plot_mse)
    print(f"report: {report}")
    for p in results["problems"]:
        print(f"problem: {p}")
    for run_name in results["diverged_runs"]:
        print(f"diverged: the simulation of {run_name} (its MSE still growing at the end: "
              "see the report; a short --steps can end inside a transient)")
    return EXIT_NEGATIVE if results["problems"] or results["diverged"] else EXIT_OK

"""``socmon chaos SCENARIO --seed S``: a live run under a random fault schedule, checked;
``--simulated A:B``: seeds A..B-1 under simulated time (:mod:`agent.run.simulated`)."""

from __future__ import annotations

from agent.protocol.timing import DEFAULT as TIMING

HELP = "run live under a random fault schedule drawn from a seed and check the invariants"


def add_arguments(parser) -> None:
    from agent.cli._common import add_force_gains_argument, add_scenario_argument

    add_scenario_argument(parser)
    parser.add_argument("--seed", type=int, default=0,
                        help="seed of the fault schedule and of the run (default 0)")
    parser.add_argument("--duration", type=int, default=1000, metavar="STEPS",
                        help="steps to run (default 1000)")
    parser.add_argument("--faults", default="kill,stop,hang,sensor,monitor,partition,delay,drop",
                        help="fault kinds to draw from (default: all of kill, stop, hang, "
                             "sensor, monitor, partition, delay, drop)")
    parser.add_argument("--rate", type=float, default=3.0,
                        help="faults per 1000 steps (default 3; at least 160 steps apart)")
    parser.add_argument("--gains", help="gains file (.npz); default: designed")
    add_force_gains_argument(parser)
    parser.add_argument("--delays", default="scenario",
                        help="link delays: scenario, none or uniform:T (default scenario)")
    parser.add_argument("--step-ms", type=float, default=None,
                        help="period of one step (default: the scenario's step_ms)")
    parser.add_argument("--hang-timeout", type=float, default=TIMING.hang_timeout_s,
                        metavar="S",
                        help=f"the monitor's hang timeout (default {TIMING.hang_timeout_s:g} s)")
    parser.add_argument("--out", help="run folder (default runs/chaos-<scenario>-s<seed>-<time>); "
                             "a folder holding an earlier run is refused")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace the earlier run in --out (its files only)")
    parser.add_argument("--simulated", metavar="A:B",
                        help="no processes: run seeds A..B-1 under simulated time "
                             "(agent.run.simulated: world, agents and monitors in this process) "
                             "and report them together; --faults may add slow, monitorstop "
                             "and monitorsgone, without linkdown or worldstop")
    parser.add_argument("--json", action="store_true", help="print the report as JSON")
    parser.add_argument("--quiet", action="store_true", help="no progress on stderr")


def run(args) -> int:
    from agent.cli._common import run_command

    return run_command(lambda: _chaos(args))


def _chaos(args) -> int:
    import json
    import sys

    from agent.cli._common import parse_int, to_jsonable, versioned
    from agent.run.chaos import live_chaos
    from agent.run.simulated import report_lines, simulated_chaos

    if args.simulated:
        first, _, last = str(args.simulated).partition(":")
        a = parse_int(first, "--simulated")
        b = parse_int(last, "--simulated", lo=a + 1) if last else a + 1
        report = simulated_chaos(args, range(a, b))
        name, kinds = report.pop("scenario_name"), report.pop("kinds")
        if args.json:
            print(json.dumps(to_jsonable(versioned(report)), indent=2))
        else:
            print(f"{name} under simulated time, seeds {a}..{b - 1}, faults "
                  f"{','.join(kinds)}, rate {args.rate:g}")
            print("\n".join(report_lines(report)))
        return 1 if report["violations"] else 0

    def say(text):
        if not args.quiet:
            print(f"chaos: {text}", file=sys.stderr, flush=True)

    report, status, reassignments = live_chaos(args, say)
    if not report["faults"]:
        print("chaos: warning: no fault was drawn (--rate, --duration): the run tested "
              "nothing", file=sys.stderr)
    if args.json:
        print(json.dumps(to_jsonable(report), indent=2))
    else:
        violations = report["violations"]
        print(f"{report['scenario']}, seed {args.seed}: {len(report['faults'])} faults, "
              f"{len(report['failures'])} verdicts, {reassignments} reassignments, "
              f"{len(violations)} violations")
        for v in violations:
            print(f"  VIOLATION {v['invariant']} at step {v['step']}: {v['evidence']}")
        print(f"run folder: {report['out']}")
        if violations or report["error"]:
            print(f"replay: {report['replay']}")
    if report["error"]:
        print(f"socmon chaos: {report['error']}", file=sys.stderr)
    return status

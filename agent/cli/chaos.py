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


def _simulated(args) -> int:
    """``--simulated A:B``: many seeds under simulated time, one report."""
    import json

    from design.errors import ScenarioError
    from design.scenario import resolve_delays

    from agent.run.simulated import FAULT_KINDS, report_lines, run_schedules
    from agent.cli._common import CommandError, load_scenario_arg, parse_int, to_jsonable, versioned
    from agent.cli.agent_cmd import gains_for

    first, _, last = str(args.simulated).partition(":")
    a = parse_int(first, "--simulated")
    b = parse_int(last, "--simulated", lo=a + 1) if last else a + 1
    kinds = tuple(k.strip() for k in args.faults.split(",") if k.strip())
    bad = [k for k in kinds if k not in FAULT_KINDS or k == "crash"]
    if bad or not kinds:
        raise CommandError(f"--faults: {bad} cannot be simulated (simulated: "
                           f"{', '.join(k for k in FAULT_KINDS if k != 'crash')})"
                           if bad else "--faults: give at least one kind")
    scenario = load_scenario_arg(args.scenario)
    try:
        delays = resolve_delays(scenario, args.delays)
    except ScenarioError as exc:
        raise CommandError(str(exc)) from None
    G = gains_for(scenario, args.gains, delays, args.force_gains)
    report = run_schedules(scenario, G, delays, range(a, b), args.duration, kinds, args.rate)
    if args.json:
        print(json.dumps(to_jsonable(versioned({**report, "delays": delays})), indent=2))
    else:
        print(f"{scenario.name} under simulated time, seeds {a}..{b - 1}, faults "
              f"{','.join(kinds)}, rate {args.rate:g}")
        print("\n".join(report_lines(report)))
    return 1 if report["violations"] else 0


def _chaos(args) -> int:
    import argparse
    import dataclasses
    import json
    import sys
    import time
    from pathlib import Path

    from agent.run.chaos import CHAOS_KINDS, check_invariants, draw_schedule
    from agent.run.summary import run_and_summarize, write_run_folder
    from agent.run.jsonable import SCHEMA_VERSION
    from agent.cli._common import CommandError, to_jsonable
    from agent.cli.up import run_config

    if not 0 <= args.rate <= 6.25:
        raise CommandError(f"--rate: must be in [0, 6.25] faults per 1000 steps, got {args.rate}")
    if args.duration < 100:
        raise CommandError(f"--duration: must be >= 100 steps, got {args.duration}")
    if args.simulated:
        return _simulated(args)
    kinds = tuple(k.strip() for k in args.faults.split(",") if k.strip())
    bad = [k for k in kinds if k not in CHAOS_KINDS]
    if bad or not kinds:
        raise CommandError(f"--faults: unknown kinds {bad} (known: {', '.join(CHAOS_KINDS)})"
                           if bad else "--faults: give at least one kind")

    def say(text):
        if not args.quiet:
            print(f"chaos: {text}", file=sys.stderr, flush=True)

    out = args.out or str(Path("runs") / f"chaos-{Path(args.scenario).stem}-s{args.seed}-"
                                          f"{time.strftime('%Y%m%d-%H%M%S')}")
    up_args = argparse.Namespace(
        scenario=args.scenario, steps=args.duration, gains=args.gains, seed=args.seed,
        out=out, delays=args.delays, step_ms=args.step_ms, deadline_ms=None,
        start_timeout=TIMING.start_timeout_s, quiet=args.quiet, no_monitor=False, monitors=2, drop=0.0,
        kill=[], stop=[],
        kill_monitor=None, hang_timeout=args.hang_timeout,
        hang_timeout_max=TIMING.hang_timeout_max_s, check_simulator=False,
        overwrite=args.overwrite)
    config = run_config(up_args, say, prog="chaos")
    schedule = draw_schedule(config.scenario, args.seed, args.duration, kinds, args.rate,
                             config.step_ms)
    config = dataclasses.replace(config, faults=tuple(schedule))
    (config.out / "schedule.json").write_text(json.dumps(
        [f.to_dict() for f in schedule], indent=2) + "\n")
    say(f"{len(schedule)} faults: " + ", ".join(
        f"{f.kind}{' ' + str(f.agent) if f.agent else ''}@{f.step}" for f in schedule))
    s = config.scenario
    rec, summary, steps, mse, predicted = run_and_summarize(config, say)
    violations = [] if rec.failure else check_invariants(config, rec, summary, steps, mse)
    write_run_folder(config.out, summary, steps, mse, predicted, assigns=rec.assigns)
    report = {
        "schema_version": SCHEMA_VERSION,
        "scenario": s.name, "seed": args.seed, "duration": args.duration,
        "faults": [f.to_dict() for f in schedule],
        "failures": summary.get("failures", []),
        "rosters": summary.get("rosters", []),
        "violations": [v.to_dict() for v in violations],
        "error": rec.failure,
        "replay": f"socmon chaos {args.scenario} --seed {args.seed} --duration "
                  f"{args.duration} --faults {','.join(kinds)} --rate {args.rate:g}",
        "out": str(config.out),
    }
    (config.out / "invariants.json").write_text(json.dumps(to_jsonable(report), indent=2) + "\n")
    _timeline(config.out, summary, steps, mse, schedule, rec.rosters)
    if args.json:
        print(json.dumps(to_jsonable(report), indent=2))
    else:
        print(f"{s.name}, seed {args.seed}: {len(schedule)} faults, "
              f"{len(summary.get('failures', []))} verdicts, "
              f"{len(rec.rosters) - 1} reassignments, {len(violations)} violations")
        for v in violations:
            print(f"  VIOLATION {v.invariant} at step {v.step}: {v.evidence}")
        print(f"run folder: {config.out}")
        if violations or rec.failure:
            print(f"replay: {report['replay']}")
    if rec.failure:
        print(f"socmon chaos: {rec.failure}", file=sys.stderr)
        return 1
    return 1 if violations else 0


def _timeline(out, summary, steps, mse, schedule, rosters):
    """timeline.json and timeline.png: faults, verdicts, activations, MSE."""
    import json

    import numpy as np

    from agent.cli._common import to_jsonable

    items = [{"step": f.step, "what": "fault", **f.to_dict()} for f in schedule]
    items += [{"step": v["detected_step"], "what": "verdict", "agent": v["agent"],
               "cause": v["cause"]} for v in summary.get("failures", [])]
    items += [{"step": at, "what": "activation", "ids": list(ids), "epoch": ep}
              for at, ids, ep in rosters[1:]]
    items.sort(key=lambda x: x["step"])
    (out / "timeline.json").write_text(json.dumps(to_jsonable(items), indent=2) + "\n")
    from agent.run.summary import plottable, pyplot

    plt = pyplot()
    if plt is None:
        return
    ok = plottable(mse)
    mse = np.asarray(mse, dtype=float)
    fig, (ax, lane) = plt.subplots(2, 1, figsize=(9, 5), sharex=True,
                                   gridspec_kw={"height_ratios": [3, 1.4]})
    ax.semilogy(np.asarray(steps)[ok], mse[ok], lw=0.8, label="MSE (live)")
    ax.set_ylabel("MSE")
    ax.set_title(f"{summary['scenario']}: chaos, seed {summary['seed']}")
    M = summary["agents"] + summary["standby"]
    colours = {"kill": "tab:red", "stop": "tab:orange", "partition": "tab:purple",
               "delay": "tab:brown", "drop": "tab:olive", "monitor": "k", "crash": "tab:red",
               "hang": "tab:pink", "sensor": "tab:cyan"}
    for f in schedule:
        y = f.agent if f.agent else 0
        width = max(1.0, f.seconds * 1000.0 / summary["step_ms"]) if f.seconds else 3
        lane.barh(y, width, left=f.step, height=0.6, color=colours.get(f.kind, "grey"),
                  alpha=0.8)
        lane.text(f.step, y + 0.35, f.kind, fontsize=7)
        ax.axvline(f.step, color=colours.get(f.kind, "grey"), lw=0.6, alpha=0.6)
    for v in summary.get("failures", []):
        lane.plot(v["detected_step"], v["agent"], "kx", ms=6)
    for at, ids, _ in rosters[1:]:
        ax.axvline(at, color="tab:green", lw=0.8, ls="--")
        for a in ids:
            lane.plot(at, a, "g|", ms=10)
    lane.set_yticks(range(0, M + 1), ["monitor"] + [f"agent {a}" for a in range(1, M + 1)])
    lane.set_xlabel("step  (bars: faults; x: verdicts; green: activations)")
    ax.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    try:
        fig.savefig(out / "timeline.png", dpi=110)
    finally:
        plt.close(fig)

"""``socmon simulate SCENARIO --gains FILE ...``: Monte-Carlo MSE of the distributed estimator.

Runs :func:`design.simulate.simulate` (timeline and conventions in docs/simulation.md).
Exit status: 0 when the run stays bounded, 1 when it diverged (or ``--recover`` finds no
recovery / no stabilising gain for it), 2 for bad input (named in the message).
"""

from __future__ import annotations


from agent.cli._common import (
    EXIT_NEGATIVE,
    EXIT_OK,
    CommandError,
    add_gains_argument,
    add_scenario_argument,
    load_gains_arg,
    load_scenario_arg,
    parse_drop,
    parse_fail,
    parse_int,
    print_json,
    resolve_delays_arg,
    run_command,
)
from agent.cli._progress import ProgressBar, ProgressLine

HELP = "Monte-Carlo simulation: mean-squared error over time, with delays, drops, failures"


def add_arguments(parser) -> None:
    add_scenario_argument(parser)
    add_gains_argument(parser)
    parser.add_argument("--trials", default="20", metavar="T",
                        help="Monte-Carlo trials (default 20)")
    parser.add_argument("--steps", default="300", metavar="K", help="time steps (default 300)")
    parser.add_argument("--seed", default="0", metavar="S",
                        help="seed of every random number (default 0)")
    parser.add_argument("--delays", default="scenario", metavar="SPEC",
                        help="link delays: scenario (default), none or uniform:T")
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
    parser.add_argument("--json", action="store_true", help="print JSON instead of text")


def run(args) -> int:
    return run_command(lambda: _run(args))


# ---------------------------------------------------------------------------------
# recovery


def build_recovery(scenario, failed, delay_spec, seed: int, objective: str = "rho",
                   previous=None, **design_options):
    """:func:`design.reconfigure.build_recovery` (warm started from ``previous``, the
    gains before the failure); its RecoveryDesignError becomes a CommandError (status 1)."""
    from design.reconfigure import RecoveryDesignError
    from design.reconfigure import build_recovery as _build

    try:
        return _build(scenario, failed, delay_spec, seed=seed, objective=objective,
                      previous=previous, **design_options)
    except RecoveryDesignError as exc:
        raise CommandError(f"--recover: {exc}", status=EXIT_NEGATIVE) from None


# ---------------------------------------------------------------------------------


def _run(args) -> int:
    from design.closed_loop import exact_performance
    from design.errors import SocmonError
    from design.simulate import simulate

    trials = parse_int(args.trials, "--trials", lo=1)
    steps = parse_int(args.steps, "--steps", lo=1)
    seed = parse_int(args.seed, "--seed", lo=0)
    drop = parse_drop(args.drop)
    if args.plot:
        from agent.cli._plot import figure_path

        args.plot = figure_path(args.plot)
    scenario = load_scenario_arg(args.scenario)
    gains = load_gains_arg(args.gains, scenario, force=args.force_gains)
    delays = resolve_delays_arg(scenario, args.delays)
    fail = parse_fail(args.fail, scenario, steps) if args.fail is not None else None
    if args.recover and fail is None:
        raise CommandError("--recover: needs --fail STEP:AGENTS")
    if fail is not None and not args.recover and len(fail[1]) == scenario.N:
        raise CommandError("--fail: every agent fails; nothing is left to estimate "
                           "(use --recover)")
    if args.time_limit is not None and not (args.recover and args.time_limit > 0):
        raise CommandError("--time-limit: a positive number of seconds, with --recover only")
    recover, recovery_info = None, None
    if args.recover:
        objective = gains.meta.get("objective")
        objective = objective if objective in ("rho", "mse") else "rho"
        budget = {} if args.time_limit is None else {"time_limit": args.time_limit}
        with ProgressLine("simulate --recover", enabled=not args.json) as line:
            line.context = "gains for the recovered network"
            recover, recovery_info = build_recovery(scenario, fail[1], args.delays, seed,
                                                     objective, previous=gains.G,
                                                     progress=line.design, **budget)
        recovery_info["objective"] = objective

    bar = ProgressBar("simulate")
    bar.enabled = bar.enabled and not args.json
    try:
        result = simulate(scenario, gains.G, steps=steps, trials=trials, seed=seed,
                          delays=delays, drop=drop, fail=fail, recover=recover, progress=bar)
    except SocmonError as exc:
        raise CommandError(str(exc)) from None
    except MemoryError:
        raise CommandError(f"--steps/--trials: {trials} trials x {steps} steps do not fit in "
                           "memory; run fewer") from None
    finally:
        bar.close()

    out = result.to_dict()
    lo, hi = result.band()
    out["mse_p10"], out["mse_p90"] = lo.tolist(), hi.tolist()
    out["scenario"] = scenario.name
    out["gains_file"] = str(args.gains)
    out["delays"] = delays.tolist()
    out["delays_spec"] = args.delays
    exact = fail is None and drop == 0   # the loop simulated is the one certify sees
    before = exact_performance(scenario, gains.G, delays) if exact or recover else None
    out["mse_steady_exact"] = before.mse if exact else None
    out["rho_exact"] = before.rho if exact else None
    out["unstable"] = out["rho_exact"] is not None and not out["rho_exact"] < 1
    if recovery_info is not None:
        out["recovery"] = recovery_info
    if args.plot:
        from agent.cli._plot import plot_mse

        events = []
        if fail is not None:
            what = "failure + recovery" if recover is not None else "failure"
            events.append((fail[0], f"{what} (agents {', '.join(str(a + 1) for a in fail[1])})"))
        ref = [(out["mse_steady_exact"], "exact steady MSE (Lyapunov)")]
        after = (recovery_info or {}).get("mse_steady_exact_after_recovery")
        if after is not None and drop == 0:
            ref = [(before.mse, "exact steady MSE before the failure"),
                   (after, "exact steady MSE after recovery")]
        try:
            plot_mse(args.plot, [(f"{scenario.name}, {trials} trials", result)],
                     title=f"{scenario.name} (delays: {args.delays})"
                           + (f", drop {drop:g}" if drop else ""),
                     events=events, reference=ref)
        except OSError as exc:
            raise CommandError(f"--plot: cannot write {args.plot!r}: {exc.strerror}") from None
        out["plot"] = str(args.plot)
    if args.json:
        print_json(out)
    else:
        print(format_text(out))
    return EXIT_NEGATIVE if result.diverged or out["unstable"] else EXIT_OK


def _f(x, digits=5) -> str:
    if x is None:
        return "-"
    return f"{x:.{digits}g}" if isinstance(x, float) else str(x)


def format_text(d: dict) -> str:
    mse = d["mse"]
    lines = [
        f"scenario {d['scenario']}, gains {d['gains_file']}: {d['trials']} trials x "
        f"{d['steps']} steps, seed {d['seed']}"
        + (f", drop {d['drop']:g}" if d["drop"] else ""),
    ]
    if d["fail_step"] is not None:
        lines.append(f"failure of agents {d['failed']} at step {d['fail_step']}"
                     + (" with recovery" if d["recovered"] else " (no recovery)"))
    if "recovery" in d:
        r = d["recovery"]
        for rep in r["replacements"]:
            lines.append(f"  node {rep['from']} of agent {rep['failed']} -> node {rep['to']} "
                         f"measured by agent {rep['by']}")
        if r["added_links"]:
            lines.append("  added links: " + ", ".join(
                f"{x['from']} -> {x['to']}" for x in r["added_links"]))
        lines.append(f"  exact radius after recovery: {r['rho_exact_after_recovery']:.6g}")
        if r.get("mse_steady_exact_after_recovery") is not None:
            lines.append("  exact steady MSE after recovery (Lyapunov): "
                         f"{_f(r['mse_steady_exact_after_recovery'])}"
                         + (" (without the drops)" if d["drop"] else ""))
    lines.append(f"MSE at step 0: {_f(mse[0] if isinstance(mse[0], float) else mse[0])}, "
                 f"at step {d['steps']}: {_f(mse[-1] if isinstance(mse[-1], float) else mse[-1])}")
    lines.append(f"steady MSE (mean over the last quarter): {_f(d['mse_steady'])}")
    if d.get("mse_steady_exact") is not None:
        lines.append(f"exact steady MSE (Lyapunov):            {_f(d['mse_steady_exact'])}")
    if d.get("rho_exact") is not None:
        lines.append(f"exact radius of the loop:               {d['rho_exact']:.6g}")
    if d.get("unstable"):
        lines.append("UNSTABLE: the exact radius is >= 1, so the error grows without bound "
                     "(a short run may not show it yet)")
    lines.append("DIVERGED" if d["diverged"] else "bounded over this run (did not diverge)")
    if d.get("plot"):
        lines.append(f"figure: {d['plot']}")
    return "\n".join(lines)

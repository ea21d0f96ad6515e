"""``socmon design``: design the agents' gains and write the gains file.

Exit status: 0 a stabilising gain was written; 1 no stabilising gain was found (no file
unless ``--force``) or the conic solver failed; 2 bad input, or the pair is not
observable (the message names the parent SCC without a sensor).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from design.ccl import SolverError
from design.closed_loop import ClosedLoop
from design.errors import NotObservableError, ScenarioError
from design.gain_design import DesignError, design_gains
from design.gains import gains_meta, load_gains, save_gains
from design.scenario import resolve_delays

from agent.cli._common import (
    EXIT_BAD_INPUT,
    EXIT_NEGATIVE,
    EXIT_OK,
    CommandError,
    add_scenario_argument,
    int_flag,
    load_scenario_arg,
    print_json,
    run_command,
)
from agent.cli._progress import ProgressLine

HELP = "design the agents' gains (the paper's LMI method or the delay-aware default)"


def add_arguments(parser) -> None:
    add_scenario_argument(parser)
    parser.add_argument("--method", choices=("default", "ccl"), default="default",
                        help="default: first-order design on the exact delayed loop; "
                             "ccl: the paper's LMI algorithm (delay-free)")
    parser.add_argument("--delays", default="scenario", metavar="scenario|none|uniform:T",
                        help="delay matrix to design for and certify against (default: scenario)")
    parser.add_argument("--objective", choices=("rho", "mse"), default=None,
                        help="minimise the exact steady MSE or the exact spectral radius "
                             "(default: mse with --method default, the gain `up` designs; "
                             "rho with --method ccl or --target)")
    parser.add_argument("--seed", type=int_flag(lo=0), default=0, help="seed of the extra starts (default 0)")
    parser.add_argument("--solver", type=str.upper, choices=("CLARABEL", "SCS"), default=None,
                        help="conic solver for --method ccl (default CLARABEL)")
    parser.add_argument("--max-iter", type=int_flag(lo=0), default=None, metavar="N",
                        help="iterations: BFGS per start and stage (default 200) or "
                             "cone-complementarity iterations (default 50)")
    parser.add_argument("--starts", type=int_flag(lo=1), default=None, metavar="K",
                        help="--method default: number of starts (default 3 for --objective "
                             "rho, 1 for mse)")
    parser.add_argument("--time-limit", type=float, default=None, metavar="SECONDS",
                        help="safety cap: stop and keep the best gain found after this long "
                             "(default: 60 s for --objective rho, whose radius converges slowly "
                             "with long delays; none for --objective mse, whose result then "
                             "does not depend on the machine's speed)")
    parser.add_argument("--window", type=int, default=None, metavar="N",
                        help="--method default: a stage stops when its objective fell by "
                             "less than --rel-tol over the last N iterations (default 20)")
    parser.add_argument("--rel-tol", type=float, default=None, metavar="X",
                        help="--method default: relative progress over --window below which "
                             "a stage stops (default 1e-3)")
    parser.add_argument("--target", type=float, default=None, metavar="RHO",
                        help="--method default, --objective rho: stop once rho < RHO")
    parser.add_argument("--no-gaps", action="store_true",
                        help="--method default: design for the nominal loop alone, without "
                             "keeping the loop each single failure leaves until the switch "
                             "(its gap) stable")
    parser.add_argument("--keep-iterating", action="store_true",
                        help="--method ccl: go on after rho < 1 to lower rho")
    parser.add_argument("--out", required=True, metavar="FILE", help="gains file to write (.npz)")
    parser.add_argument("--json", action="store_true", help="print a JSON record")
    parser.add_argument("--force", action="store_true",
                        help="write the gains file even when the design is not stabilising")


def _options(args) -> dict:
    if args.objective is None:         # the one default: the gain `socmon up` designs
        args.objective = "rho" if args.method == "ccl" or args.target is not None else "mse"
    opts = {}
    if args.method == "ccl":
        for flag, value in (("--starts", args.starts), ("--target", args.target),
                            ("--window", args.window), ("--rel-tol", args.rel_tol),
                            ("--no-gaps", args.no_gaps or None)):
            if value is not None:
                raise CommandError(f"{flag} applies to --method default only")
        if args.objective == "mse":
            raise CommandError("--objective mse needs --method default (ccl designs for rho)")
        opts["solver"] = args.solver or "CLARABEL"
        opts["keep_iterating"] = bool(args.keep_iterating)
    else:
        if args.solver is not None:
            raise CommandError("--solver applies to --method ccl only")
        if args.keep_iterating:
            raise CommandError("--keep-iterating applies to --method ccl only")
        if args.starts is not None:
            opts["starts"] = args.starts
        if args.no_gaps:
            opts["gaps"] = False
        if args.window is not None:
            if args.window < 1:
                raise CommandError(f"--window: must be at least 1, got {args.window}")
            opts["patience"] = args.window
        if args.rel_tol is not None:
            if not 0 <= args.rel_tol < 1:
                raise CommandError(f"--rel-tol: must be in [0, 1), got {args.rel_tol}")
            opts["patience_tol"] = args.rel_tol
        if args.target is not None:
            if args.objective != "rho" or not 0 < args.target:
                raise CommandError("--target: a positive radius, with --objective rho only")
            opts["target"] = args.target
    if args.max_iter is not None:
        if args.method == "default" and args.max_iter < 1:
            raise CommandError(f"--max-iter: must be a positive integer, got {args.max_iter}")
        opts["max_iter"] = args.max_iter
    if args.time_limit is not None:
        if not args.time_limit > 0:
            raise CommandError(f"--time-limit: must be positive, got {args.time_limit}")
        opts["time_limit"] = args.time_limit
    elif args.method == "default" and args.objective == "rho":
        opts["time_limit"] = 60.0
    return opts


def run(args) -> int:
    return run_command(lambda: _run(args))


def _run(args) -> int:
    scenario = load_scenario_arg(args.scenario)
    try:
        D = resolve_delays(scenario, args.delays)
    except ScenarioError as exc:
        raise CommandError(str(exc)) from None
    out = Path(args.out)
    if not out.parent.is_dir():
        raise CommandError(f"--out: folder {str(out.parent)!r} does not exist")
    if out.is_dir():
        raise CommandError(f"--out: {str(out)!r} is a folder, give a file name")
    opts = _options(args)
    line = ProgressLine("design", enabled=not args.json)
    try:
        res = design_gains(scenario, delays=D, method=args.method, objective=args.objective,
                           seed=args.seed, progress=line.design, **opts)
    except NotObservableError as exc:
        raise CommandError(str(exc), EXIT_BAD_INPUT) from None
    except SolverError as exc:
        raise CommandError(f"ccl design failed: {exc}", EXIT_NEGATIVE) from None
    except DesignError as exc:
        raise CommandError(str(exc)) from None
    finally:
        line.close()

    record = res.summary()
    record["scenario"] = scenario.name
    record["written"] = None
    if res.stable or args.force:
        meta = gains_meta(
            scenario, res.method, res.delays, res.rho, objective=res.objective,
            mse_steady_exact=res.mse_steady, stable=res.stable, seconds=res.seconds,
            iterations=res.iterations, seed=res.seed, status=res.status,
            rho_delay_free=res.rho_delay_free,
            options={k: v for k, v in res.options.items() if k != "init"},
        )
        save_gains(out, res.G, meta)
        # the radius reported is that of the file as written, computed afresh
        written = load_gains(out, scenario)
        loop = ClosedLoop(scenario.A, scenario.W, D, scenario.measure, written.G)
        record["rho_exact"] = loop.spectral_radius()
        record["stable"] = bool(record["rho_exact"] < 1)
        record["written"] = str(out)
        record["warnings"] = (_worse_than_no_correction(scenario, D, record)
                              + gap_design_warnings(record))
    status = EXIT_OK if record["stable"] else EXIT_NEGATIVE
    if args.json:
        print_json(record)
    else:
        _print_text(record, res)
    if not args.json:
        for w in record.get("warnings", []):
            print(f"socmon: warning: {w}", file=sys.stderr)
    if not record["stable"]:
        where = f"written to {out} (--force)" if record["written"] else "no file written"
        print(f"socmon: no stabilising gain found for these delays (rho = {record['rho_exact']:.6g}); "
              f"{where}", file=sys.stderr)
    return status


def gap_design_warnings(record) -> list:
    """A warning per gap (single failure) whose loop diverges with the gain designed,
    saying whether no gain could have kept it stable."""
    impossible = {g["failed"]: g["bound"]
                  for g in (record.get("gap_design") or {}).get("impossible", [])}
    out = []
    for g in record.get("gaps", []):
        if g["stable"]:
            continue
        why = (f"no gain can keep it stable (an unobservable mode of modulus "
               f"{impossible[g['failed']]:.4g})" if g["failed"] in impossible else
               "the gap terms could not keep it stable" if record["gap_design"] else
               "designed without the gap terms")
        out.append(f"if agent {g['failed']} fails, the others run a loop of exact radius "
                   f"{g['rho_exact']:.4g} until the switch: {why}; the estimates diverge if "
                   "the switch does not come within the hold window")
    return out


def _worse_than_no_correction(scenario, D, record) -> list:
    """A warning when a radius-designed gain's exact steady MSE is above that of no
    correction at all (zero gains: each agent predicts, the loop is W (x) A), which is
    possible when A is stable: the radius objective does not design for the error."""
    mse = record.get("mse_steady_exact")
    if record.get("objective") != "rho" or mse is None or not np.isfinite(mse) \
            or not record["stable"]:
        return []
    zero = ClosedLoop(scenario.A, scenario.W, D, scenario.measure,
                      [np.zeros((scenario.n, len(m))) for m in scenario.measure])
    if not zero.spectral_radius() < 1:
        return []
    none = zero.mse_steady(scenario.process_noise, scenario.measurement_noise)
    if not mse > none:
        return []
    return [f"this gain's exact steady MSE ({mse:.6g}) is above that of no correction at "
            f"all (zero gains: {none:.6g}): the radius objective does not design for the "
            "error; --objective mse does"]


def _print_text(record, res) -> None:
    delays = record["delays"]
    taubar = max((max(r) for r in delays), default=0)
    print(f"design {record['scenario']}: method {record['method']}, objective "
          f"{record['objective']}, delays up to {taubar} steps")
    print(f"  rho (exact, delays as designed for) = {record['rho_exact']:.6f}  "
          f"{'stable' if record['stable'] else 'NOT stable'}")
    print(f"  rho (delay-free loop)              = {record['rho_delay_free']:.6f}")
    if record["mse_steady_exact"] is not None:
        print(f"  steady MSE (exact)                 = {record['mse_steady_exact']:.6g}")
    det = record["detectability"]
    print(f"  distributed pair rank {det['rank']} of {det['order']}"
          f" ({'observable' if det['observable'] else 'detectable'})")
    print(f"  {record['iterations']} iterations, {record['seconds']:.2f} s; stopped: {record['status']}")
    if record["status"] == "time limit":
        print("  (the --time-limit budget ended the design: raise it for a lower "
              + ("radius, or give --target RHO to stop at a radius)"
                 if record["objective"] == "rho" else "MSE)"))
    if record.get("gaps"):
        radii = ", ".join(f"{g['failed']}: {g['rho_exact']:.4f}" for g in record["gaps"])
        print(f"  gap radii (exact; failed agent: the loop the others run until the switch)"
              f" {radii}")
        gd = record.get("gap_design") or {}
        if gd:
            before = ", ".join(f"{f}: {r:.4f}" for f, r in gd["rho_gap_before"].items())
            print(f"  gap terms (every gap below {gd['target']:.4g}): {gd['note']}"
                  + ("" if not gd["iterations"] else
                     f"; {gd['iterations']} iterations; the nominal design's gaps {before}"))
    if record["written"]:
        print(f"  gains written to {record['written']}")

"""``socmon certify SCENARIO --gains FILE [--taus 0,3,7,15] [--json]``: exact certificates.

What each figure means is documented in :mod:`design.certificates`. Exit status: 0 when
the gain is stable with the scenario's own delays (exact radius < 1), 1 when it is not,
2 for bad input (scenario, gains file, gains that do not fit, bad ``--taus``).
"""

from __future__ import annotations

from design.certificates import DEFAULT_TAU_CAP, certify
from design.scenario import MAX_DELAY

from agent.cli._common import (
    EXIT_NEGATIVE,
    EXIT_OK,
    add_gains_argument,
    add_scenario_argument,
    gains_scenario_mismatch,
    load_gains_arg,
    int_flag,
    load_scenario_arg,
    parse_int_list,
    print_json,
    run_command,
)
from agent.cli._progress import ProgressLine

HELP = "exact stability radius, Theorem 1 criterion, paper formula, steady MSE and Phi of a gain"


def add_arguments(parser) -> None:
    add_scenario_argument(parser)
    add_gains_argument(parser)
    parser.add_argument("--taus", default="0,3,7,15", metavar="T1,T2,...",
                        help="uniform inter-agent delays to certify (default 0,3,7,15)")
    parser.add_argument("--tau-cap", type=int_flag(lo=0), default=None, metavar="T",
                        help="largest tau examined in the Theorem 1 tau_star search "
                             "(default 100)")
    parser.add_argument("--json", action="store_true", help="print JSON instead of text")


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
        result = certify(scenario, gains.G, taus=taus, tau_cap=cap, progress=line.update)
    from design.gap import diverging_gaps, gap_report

    from design.scenario import uniform_delays

    gaps = gap_report(scenario, gains.G, scenario.delays)
    result["gaps"] = [g.to_dict() for g in gaps]
    for row in result["rows"]:      # the gap radii with every link delayed by the row's tau
        row["gaps_rho_exact"] = {
            str(g.failed): g.rho for g in gap_report(
                scenario, gains.G, uniform_delays(scenario.W, row["tau"]), mse=False)}
    result["gains_file"] = str(args.gains)
    result["gains_meta"] = gains.meta
    mismatch = gains_scenario_mismatch(gains.meta, scenario)   # only with --force-gains
    result["warnings"] = ([mismatch] if mismatch is not None else []) + [
        f"{line}: the estimates diverge if the switch does not come within the hold window"
        for line in diverging_gaps(gaps)]
    if args.json:
        print_json(result)
    else:
        print(format_text(result))
    return EXIT_OK if result["stable"] else EXIT_NEGATIVE


def format_gaps(gaps) -> list:
    """The table of :func:`design.gap.gap_report`'s records (``to_dict``), one line each."""
    lines = ["  failed   exact radius  stable   exact steady MSE   own-loop radii"]
    for g in gaps:
        own = ", ".join(f"{a}: {r:.4f}" for a, r in g["own_loop_radius"].items())
        lines.append(f"  {g['failed']:>6}   {g['rho_exact']:12.6f}  "
                     f"{'yes' if g['stable'] else 'NO ':<6}   "
                     f"{_f(g.get('mse_steady_exact'), 6):>16}   {own}")
    return lines


def _f(x, digits=5) -> str:
    return "-" if x is None else f"{x:.{digits}g}"


def format_text(d: dict) -> str:
    lines = [
        f"scenario {d['scenario']}, gains {d['gains_file']}",
        f"exact radius, delay-free:          {_f(d['rho_delay_free'])}"
        f" ({'stable' if d['stable_delay_free'] else 'UNSTABLE'})",
        f"exact radius, scenario delays (taubar = {d['scenario_taubar']}): "
        f"{_f(d['rho_exact'])} ({'stable' if d['stable'] else 'UNSTABLE'})",
        f"steady MSE (exact), delay-free:    {_f(d['mse_steady_delay_free'])}",
        f"steady MSE (exact), scenario delays: {_f(d['mse_steady_exact'])}",
    ]
    ts = d["tau_star"]
    if ts is None:
        lines.append("paper's Theorem 1: criterion fails already at tau = 0 (no tau_star)")
    else:
        lines.append(
            f"paper's Theorem 1: holds for tau = 0..{ts}"
            + (f" (search capped at {d['tau_star_cap']})" if d["tau_star_capped"]
               else f" (tau_star = {ts}; searched up to {d['tau_star_cap']})"))
    lines.append("")
    lines.append("  tau   exact radius  stable   exact steady MSE   paper's formula   "
                 "Theorem 1 rho  holds")
    for r in d["rows"]:
        lines.append(
            f"  {r['tau']:>3}   {r['rho_exact']:12.6f}  {'yes' if r['stable'] else 'NO ':<6}"
            f"   {_f(r['mse_steady_exact'], 6):>16}"
            f"   {r['paper_formula']:15.6f}   {r['theorem1_rho']:13.6g}  "
            f"{'yes' if r['theorem1_holds'] else 'no'}")
    lines.append("  (paper's formula = rho(Ahat)^(1/(tau+1)), Tables 2-4; not a certificate)")
    lines.append("")
    if d["phi"] is None:
        lines.append(f"paper's Phi (Remark 2): undefined: {d['phi_note']}")
    else:
        lines.append(
            f"paper's Phi (Remark 2): {_f(d['phi'], 4)} with {d['phi_beta_choice']} = "
            f"{_f(d['phi_beta'], 4)}; alpha1 = {_f(d['phi_alpha1'], 4)}, "
            f"alpha2 = {_f(d['phi_alpha2'], 4)}")
    if d.get("gaps"):
        lines.append("")
        lines.append("between a failure and the switch (scenario delays; the failed agent's "
                     "weight on its receivers' own predictions):")
        lines += format_gaps(d["gaps"])
        lines.append("  exact gap radius with every link delayed by tau (failed agent: radius):")
        for r in d["rows"]:
            lines.append(f"  {r['tau']:>5}   " + ", ".join(
                f"{f}: {rho:.6f}{'' if rho < 1 else ' NO'}"
                for f, rho in r.get("gaps_rho_exact", {}).items()))
    for warning in d.get("warnings", []):
        lines.append(f"warning: {warning}")
    return "\n".join(lines)

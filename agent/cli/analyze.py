"""``socmon analyze SCENARIO [--json]``: structure, observability, detectability, tolerance."""

from __future__ import annotations

from design.analysis import analyze

from agent.cli._common import (
    EXIT_NEGATIVE,
    EXIT_OK,
    add_force_gains_argument,
    add_scenario_argument,
    int_flag,
    load_gains_arg,
    load_scenario_arg,
    print_json,
    run_command,
)

HELP = "structural and numerical analysis of a scenario (SCCs, observability, failure tolerance)"


def add_arguments(parser) -> None:
    add_scenario_argument(parser)
    parser.add_argument("--json", action="store_true", help="print JSON instead of text")
    parser.add_argument(
        "--max-subsets", type=int_flag(lo=1), default=None, metavar="K",
        help="bound on the failure sets examined for the failure tolerance "
             "(default 20000; past it the tolerance is a lower bound)",
    )
    parser.add_argument("--gains", default=None, metavar="FILE",
                        help="also report, for these gains, the loop each single failure "
                             "leaves until the switch (exact radius and steady MSE with the "
                             "scenario's delays, own-loop radii), as certify does")
    add_force_gains_argument(parser)


def run(args) -> int:
    return run_command(lambda: _run(args))


def _run(args) -> int:
    scenario = load_scenario_arg(args.scenario)
    from design.gap import diverging_gaps, gap_possibilities, gap_report

    result = analyze(scenario, max_subsets=args.max_subsets)
    gains = None if args.gains is None else load_gains_arg(args.gains, scenario,
                                                          force=args.force_gains)
    data = result.to_dict()
    possible, own = gap_possibilities(scenario)
    data["gap_detectability"] = possible
    data["own_loop_bound"] = {str(a): b for a, b in own.items()}
    if gains is not None:
        gaps = gap_report(scenario, gains.G, scenario.delays)
        data["gaps"] = [g.to_dict() for g in gaps]
        data["gains_file"] = str(args.gains)
        data["warnings"] = list(data["warnings"]) + [
            f"{line}: the estimates diverge if the switch does not come within the hold "
            "window" for line in diverging_gaps(gaps)]
    if args.json:
        print_json(data)
    else:
        print(format_text(data))
    if not data["distributed_detectable"]:      # a negative result: no gain can help
        import sys

        print("socmon analyze: the agents' network is not detectable: no gain makes the "
              "distributed estimator's error bounded", file=sys.stderr)
        return EXIT_NEGATIVE
    return EXIT_OK


def _yes(flag) -> str:
    return "yes" if flag else "no"


def _modes(modes) -> str:
    if not modes:
        return "none"
    top = max(m["abs"] for m in modes)
    return f"{len(modes)}, largest |lambda| = {top:.4g}"


def format_text(d: dict) -> str:
    lines = [
        f"scenario {d['scenario']}: n = {d['n']} individuals, N = {d['N']} agents "
        f"(+{d['standby']} standby)",
        f"social dynamics: rho(A) = {d['rho_A']:.5g}, rank(A) = {d['rank_A']}"
        + ("" if d["full_rank"] else "  (rank deficient: Assumption 1 fails)"),
        "strongly connected components of the influence graph:",
    ]
    for c in d["sccs"]:
        kind = "parent" if c["parent"] else "child "
        lines.append(f"  {kind} {{{', '.join(c['nodes'])}}}")
    lines += [
        "equivalence classes (parent SCCs): "
        + "; ".join("{" + ", ".join(c) + "}" for c in d["equivalence_classes"]),
        f"measured nodes: {', '.join(d['measured_nodes'])}; a minimal sensor set: "
        f"{', '.join(d['minimal_sensor_set'])}",
    ]
    if d["unmeasured_parent_sccs"]:
        lines.append(
            "parent SCCs without sensor: "
            + "; ".join("{" + ", ".join(c) + "}" for c in d["unmeasured_parent_sccs"])
        )
    lines += [
        f"(A, H): structurally observable {_yes(d['structurally_observable'])}; "
        f"numerical rank {d['observability_rank']} of {d['n']} -> observable "
        f"{_yes(d['observable'])}, detectable {_yes(d['detectable'])} "
        f"(unobservable modes: {_modes(d['unobservable_modes'])})",
        f"(W (x) A, D_H): structurally (Lemma 3) {_yes(d['distributed_structurally_observable'])}; "
        f"numerical rank {d['distributed_rank']} of {d['distributed_order']} -> observable "
        f"{_yes(d['distributed_observable'])}, detectable {_yes(d['distributed_detectable'])} "
        f"(unobservable modes: {_modes(d['distributed_unobservable_modes'])})",
    ]
    if d["disagreement_reasons"]:
        lines.append("structural and numerical verdicts disagree:")
        lines += [f"  {r}" for r in d["disagreement_reasons"]]
    else:
        lines.append("structural and numerical verdicts agree")
    lines.append(
        f"agent network strongly connected: {_yes(d['network_strongly_connected'])}"
        + ("" if d["network_strongly_connected"]
           else f" (components {d['network_components']})")
    )

    def tol(key):
        p = d[key]
        exact = d.get(key + "_exact", True)
        witness = d.get(key + "_witness")
        txt = "none (not recoverable even without failures)" if p is None else str(p)
        if not exact:
            txt += " (lower bound: search limit reached)"
        if witness:
            txt += f"; e.g. agents {witness} failing together is not recoverable"
        return txt

    lines += [
        f"failure tolerance (standby agents replace, no new links): {tol('failure_tolerance')}",
        f"failure tolerance with new links allowed: {tol('failure_tolerance_with_new_links')}",
        "failure tolerance without replacement (paper's Remark 5): "
        + ("none (not recoverable even without failures)"
           if d["failure_tolerance_without_replacement"] is None
           else str(d["failure_tolerance_without_replacement"])),
    ]
    lines += _gap_lines(d)
    for w in d["warnings"]:
        lines.append(f"warning: {w}")
    return "\n".join(lines)


def _gap_lines(d) -> list:
    from agent.cli.certify import format_gaps

    lines = ["between a failure and the switch (the failed agent's weight on its receivers' "
             "own predictions):"]
    if d["gap_detectability"] is None:
        lines.append("  whether a gain can keep each gap stable: not examined (n (N - 1) "
                     "above the analysis limit)")
    else:
        for g in d["gap_detectability"]:
            lines.append(
                f"  agent {g['failed']} fails: "
                + ("a gain can keep the gap stable" if g["detectable"] else
                   "NO gain keeps the gap stable")
                + f" (largest unobservable modulus {g['max_unobservable_modulus']:.4g})")
    lines.append("  lowest own-loop radius any gain gives (an agent alone on its readings): "
                 + ", ".join(f"{a}: {b:.4g}" for a, b in d["own_loop_bound"].items()))
    if d.get("gaps"):
        lines.append(f"  with the gains of {d['gains_file']} (scenario delays):")
        lines += ["  " + line for line in format_gaps(d["gaps"])]
    return lines

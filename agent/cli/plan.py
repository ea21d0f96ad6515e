"""``socmon plan SCENARIO --fail 1,2 [--json]``: recovery plan after agent failures.

The policy (which node replaces a lost one, who measures it, how W is rebuilt, which
links are added) is documented in :mod:`design.recovery`. Exit status: 0 when the new
configuration is recoverable (an agent left, every parent SCC measured, network strongly
connected, links added if allowed) and its distributed pair (W' (x) A, D_H') is
detectable, so that a stabilising gain exists; 1 when not; 2 for bad input. ``--write-scenario FILE`` writes the new
configuration as a scenario TOML, ready for ``socmon design`` / ``certify``.
"""

from __future__ import annotations

from pathlib import Path

from design.recovery import plan_recovery
from design.scenario import scenario_to_toml

from agent.cli._common import (
    EXIT_NEGATIVE,
    EXIT_OK,
    CommandError,
    add_scenario_argument,
    load_scenario_arg,
    parse_agent_list,
    print_json,
    run_command,
)

HELP = "recovery plan after agent failures: replacements, new W, added links, observability"


def add_arguments(parser) -> None:
    add_scenario_argument(parser)
    parser.add_argument("--fail", required=True, metavar="IDS",
                        help="failed agent ids, comma-separated (agents are 1..N)")
    parser.add_argument("--no-new-links", action="store_true",
                        help="do not add links even if the agent network falls apart")
    parser.add_argument("--write-scenario", metavar="FILE", default=None,
                        help="write the recovered configuration as a scenario TOML file")
    parser.add_argument("--json", action="store_true", help="print JSON instead of text")


def run(args) -> int:
    return run_command(lambda: _run(args))


def _run(args) -> int:
    scenario = load_scenario_arg(args.scenario)
    failed = parse_agent_list(args.fail, scenario, flag="--fail")
    plan = plan_recovery(scenario, failed, add_links=not args.no_new_links)
    data = {"scenario": scenario.name, **plan.to_dict(scenario)}
    if args.no_new_links:
        data["no_new_links"] = True
    if args.write_scenario:
        if plan.scenario_after is None:
            raise CommandError(
                "--write-scenario: no recovered configuration to write (no agent left or "
                "the agent network is not strongly connected)", status=EXIT_NEGATIVE)
        path = Path(args.write_scenario)
        try:
            path.write_text(scenario_to_toml(plan.scenario_after))
        except OSError as exc:
            raise CommandError(f"--write-scenario: cannot write {path}: {exc.strerror}") from None
        data["scenario_written"] = str(path)
    if args.json:
        print_json(data)
    else:
        print(format_text(data))
    ok = _recoverable_as_planned(data) and data.get("distributed_detectable_after", False)
    return EXIT_OK if ok else EXIT_NEGATIVE


def _recoverable_as_planned(d: dict) -> bool:
    """Recoverable with the links this plan may add (none with ``--no-new-links``)."""
    return d["recoverable_without_new_links"] if d.get("no_new_links") else d["recoverable"]


def format_text(d: dict) -> str:
    lines = [f"failed agents: {d['failed']}"]
    for a in map(str, d["failed"]):
        cands = d["candidates"].get(a, [])
        line = f"  agent {a}: equivalent nodes {', '.join(cands) if cands else 'none'}"
        if a in d["no_equivalent"]:
            line += f"; nodes {', '.join(d['no_equivalent'][a])} are in child SCCs (no equivalent, not needed)"
        if a in d["unrecoverable_nodes"]:
            line += f"; nodes {', '.join(d['unrecoverable_nodes'][a])} have no equivalent (single-node parent SCC)"
        if a in d["unassigned_nodes"]:
            line += f"; nodes {', '.join(d['unassigned_nodes'][a])} not replaced: no agent left"
        lines.append(line)
    lines.append("replacements:")
    if not d["replacements"]:
        lines.append("  none")
    for a, r in d["replacements"].items():
        for e in [r] + r.get("also", []):
            who = f"standby agent {e['by']}" if e["by_standby"] else f"agent {e['by']}"
            lines.append(f"  agent {a}: node {e['from']} -> node {e['to']}, measured by {who}")
    lines.append(f"agents after: {d['agents_after']} (rows of the new W, in order)")
    lines.append(
        "network after removing the failed agents: "
        + ("strongly connected" if d["network_strongly_connected_removed"]
           else f"NOT strongly connected, components {d['network_components_removed']}")
    )
    if d["added_links"]:
        lines.append("links added (fewest that restore strong connectivity): "
                     + ", ".join(f"{e['to']} listens to {e['from']}" for e in d["added_links"]))
    lines.append(f"network strongly connected after: "
                 f"{'yes' if d['network_strongly_connected_after'] else 'no'}")
    lines.append("W after:")
    for row in d["W_after"]:
        lines.append("  " + " ".join(f"{x:6.3f}" for x in row))
    lines.append(f"measure after: {d['measure_after']}")
    if d.get("observability_rank_after") is not None:
        lines.append(
            f"(A, H) after: rank {d['observability_rank_after']} -> observable "
            f"{'yes' if d['observable_after'] else 'no'}; (W (x) A, D_H) after: rank "
            f"{d['distributed_rank_after']} of {d['distributed_order_after']}, detectable "
            f"{'yes' if d['distributed_detectable_after'] else 'no'}"
        )
    if d["unmeasured_parent_sccs_after"]:
        lines.append("parent SCCs left without sensor: " + "; ".join(
            "{" + ", ".join(c) + "}" for c in d["unmeasured_parent_sccs_after"]))
    if d.get("no_new_links"):
        lines.append("recoverable without new links: "
                     + ("yes" if d["recoverable_without_new_links"] else "no")
                     + ("" if d["recoverable_without_new_links"] or not d["recoverable"]
                        else " (yes if plan may add links: drop --no-new-links)"))
    else:
        lines.append("recoverable: " + ("yes" if d["recoverable"] else "no"))
    if "scenario_written" in d:
        lines.append(f"recovered scenario written to {d['scenario_written']}")
    return "\n".join(lines)

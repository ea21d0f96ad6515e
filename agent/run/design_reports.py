"""The design-side commands (``socmon analyze``, ``certify``, ``plan``, ``design``): their
records with the files they read and write, and the text they print.

The numbers and warnings come from :mod:`design.reports`; this module adds what only the
command line knows (the gains file read, the gains file or scenario written, the flags
that go together) and says the records in words. Bad input is an InputError naming the
flag (exit 2); a negative result is one of status 1.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from design.analysis import analyze
from design.ccl import SolverError
from design.errors import NotObservableError, ScenarioError
from design.gain_design import DesignError, design_gains
from design.gains import gains_meta, load_gains, save_gains
from design.recovery import plan_recovery
from design.reports import analysis_record, certificate_record, recheck_design, recovery_record
from design.scenario import resolve_delays, scenario_to_toml

from agent.run.inputs import (
    EXIT_BAD_INPUT,
    EXIT_NEGATIVE,
    InputError,
    gains_scenario_mismatch,
    load_gains_arg,
)

__all__ = ["gains_words", "tolerance_why", "redundancy_why", "analysis_report",
           "format_analysis", "certificate_report", "format_certificates", "format_gaps",
           "plan_report", "format_plan", "DesignRequest", "design_request", "design_for",
           "design_report", "design_notes", "format_design"]


def _yes(flag) -> str:
    return "yes" if flag else "no"


def _f(x, digits=5) -> str:
    return "-" if x is None else f"{x:.{digits}g}"


def _sets(components) -> str:
    return "; ".join("{" + ", ".join(c) + "}" for c in components)


def format_gaps(gaps) -> list:
    """The table of :func:`design.gap.gap_report`'s records (``to_dict``), one line each.

    >>> print("\\n".join(format_gaps([{"failed": 2, "rho_exact": 1.25, "stable": False,
    ...     "mse_steady_exact": None, "own_loop_radius": {"1": 0.5}}])))
      failed   exact radius  stable   exact steady MSE   own-loop radii
           2       1.250000  NO                      -   1: 0.5000
    """
    lines = ["  failed   exact radius  stable   exact steady MSE   own-loop radii"]
    for g in gaps:
        own = ", ".join(f"{a}: {r:.4f}" for a, r in g["own_loop_radius"].items())
        lines.append(f"  {g['failed']:>6}   {g['rho_exact']:12.6f}  "
                     f"{'yes' if g['stable'] else 'NO ':<6}   "
                     f"{_f(g.get('mse_steady_exact'), 6):>16}   {own}")
    return lines


def gains_words(meta: dict) -> str:
    """What a gains file's ``meta`` says of it (:func:`design.gains.gains_meta`): how it was
    designed and the exact figures recorded when it was, for the delays it was designed
    for; empty for a file that records none of them (written by hand).

    >>> gains_words({"method": "default", "objective": "mse", "delays": [[0, 3], [3, 0]],
    ...              "rho_exact": 0.93, "mse_steady_exact": 0.27})
    'method default, objective mse; as designed (taubar 3): exact radius 0.93, exact steady MSE 0.27'
    >>> gains_words({"method": "bench"})
    'method bench'
    """
    said = []
    if meta.get("method"):
        said.append(f"method {meta['method']}")
    if meta.get("objective"):
        said.append(f"objective {meta['objective']}")
    figures = []
    if meta.get("rho_exact") is not None:
        figures.append(f"exact radius {_f(meta['rho_exact'], 6)}")
    if "mse_steady_exact" in meta:
        figures.append("exact steady MSE " + (_f(meta["mse_steady_exact"], 6)
                                              if meta["mse_steady_exact"] is not None
                                              else "not recorded"))
    text = ", ".join(said)
    if figures:
        delays = meta.get("delays")
        taubar = (f" (taubar {max((max(r) for r in delays), default=0)})"
                  if isinstance(delays, list) and delays and isinstance(delays[0], list) else "")
        text += ("; " if text else "") + f"as designed{taubar}: " + ", ".join(figures)
    return text


# -- socmon analyze -------------------------------------------------------------------

def analysis_report(scenario, max_subsets=None, gains_file=None, force_gains=False) -> dict:
    """The record ``socmon analyze`` prints (:func:`design.reports.analysis_record`),
    with the gap loops of the gains in ``gains_file`` when given (``gains_file`` names it)."""
    result = analyze(scenario, max_subsets=max_subsets)
    gains = None if gains_file is None else load_gains_arg(gains_file, scenario,
                                                            force=force_gains)
    data = analysis_record(result, None if gains is None else gains.G)
    # why the smallest failing set found fails, in the words of `plan`
    for key, allow in (("failure_tolerance", False), ("failure_tolerance_with_new_links", True)):
        witness = data.get(key + "_witness")
        data[key + "_why"] = (None if not witness else
                              tolerance_why(scenario, [a - 1 for a in witness], allow))
    red = result.redundancy_tolerance
    witness = None if red is None or red.witness is None else list(red.witness)
    data["failure_tolerance_without_replacement_witness"] = (
        None if witness is None else [a + 1 for a in witness])
    data["failure_tolerance_without_replacement_why"] = (
        None if not witness else redundancy_why(scenario, witness))
    if gains is not None:
        data["gains_file"] = str(gains_file)
        data["gains_meta"] = gains.meta
    return data


def tolerance_why(scenario, failed, allow_new_links: bool) -> str:
    """Why the failure of the agents ``failed`` (0-based) is not recoverable by the
    recovery policy (:func:`design.recovery.plan_recovery`, standbys replace), in the
    words ``socmon plan`` uses.

    >>> from design.scenario import load_scenario
    >>> tolerance_why(load_scenario("paper-14"), [0, 1], allow_new_links=False)
    'without agents 1 and 2 the agents left are not strongly connected (components {3}, {4}) and no link may be added'
    """
    plan = plan_recovery(scenario, failed, add_links=allow_new_links, numerical=False)
    lab = scenario.labels
    who = _agents_words([a + 1 for a in plan.failed])
    out = []
    for a in plan.failed:
        if plan.unrecoverable.get(a):
            out.append(f"agent {a + 1}'s {_nodes_words(lab, plan.unrecoverable[a])} no "
                       "equivalent (a parent SCC of one node)")
        if plan.unassigned.get(a):
            out.append(f"agent {a + 1}'s {_nodes_words(lab, plan.unassigned[a])} equivalents "
                       "but no agent is left to measure them")
    if not plan.agent_ids:
        out.append(f"no agent is left without {who}")
    elif plan.unmeasured_parents_after and not out:
        out.append("parent SCC(s) left without sensor: " + "; ".join(
            "{" + ", ".join(lab[v] for v in c) + "}" for c in plan.unmeasured_parents_after))
    if not allow_new_links and plan.agent_ids and not plan.network_strongly_connected_removed:
        child = [a for a in plan.failed if plan.no_equivalent.get(a)
                 and not plan.candidates_by_node.get(a)]
        out.append((f"{_agents_words([a + 1 for a in child])} "
                    + ("measures" if len(child) == 1 else "measure") + " only nodes of child "
                    "SCCs (no equivalent, not needed: no standby takes the place), and "
                    if child else "")
                   + f"without {who} the agents left are not strongly connected (components "
                     + ", ".join("{" + ", ".join(map(str, sorted(c))) + "}"
                                 for c in sorted(plan.components_removed, key=min))
                     + ") and no link may be added")
    return "; ".join(out) or "not recoverable"


def redundancy_why(scenario, failed) -> str:
    """Why the survivors of the failure of ``failed`` (0-based), with no replacement (the
    paper's Remark 5), cannot go on: a parent SCC none of them measures, or their network
    not strongly connected.

    >>> from design.scenario import load_scenario
    >>> redundancy_why(load_scenario("paper-14"), [0])
    'without agent 1 no agent left measures the parent SCC {6, 7, 8} (nobody replaces it here), and the agents left are not strongly connected'
    """
    from design.connectivity import agent_flow_graph, is_strongly_connected
    from design.graph import influence_structure

    structure = influence_structure(scenario.A)
    alive = [i for i in range(scenario.N) if i not in set(failed)]
    covered = {int(structure.labels[v]) for i in alive for v in scenario.measure[i]}
    lab = scenario.labels
    who = _agents_words([a + 1 for a in failed])
    lost = [c for c in structure.parents if int(c) not in covered]
    out = []
    if not alive:
        return f"no agent is left without {who}"
    if lost:
        out.append(f"without {who} no agent left measures the parent SCC"
                   + ("s " if len(lost) > 1 else " ") + "; ".join(
                       "{" + ", ".join(lab[v] for v in structure.components[c]) + "}"
                       for c in lost) + " (nobody replaces it here)")
    if len(alive) > 1 and not is_strongly_connected(
            agent_flow_graph(np.asarray(scenario.W)[np.ix_(alive, alive)])):
        out.append("the agents left are not strongly connected" if out else
                   f"without {who} the agents left are not strongly connected")
    return ", and ".join(out) or "not recoverable"


def _nodes_words(labels, nodes) -> str:
    """``node 7 has`` / ``nodes 7, 9 have`` (0-based ``nodes``, named by label)."""
    names = [labels[v] for v in nodes]
    return (f"node {names[0]} has" if len(names) == 1 else f"nodes {', '.join(names)} have")


def _agents_words(ids) -> str:
    """``agent 1`` / ``agents 1 and 2`` / ``agents 1, 2 and 3``."""
    ids = [str(a) for a in ids]
    if len(ids) == 1:
        return f"agent {ids[0]}"
    return f"agents {', '.join(ids[:-1])} and {ids[-1]}"


def _modes(modes) -> str:
    if not modes:
        return "none"
    top = max(m["abs"] for m in modes)
    return f"{len(modes)}, largest |lambda| = {top:.4g}"


def format_analysis(d: dict) -> str:
    """The text of an :func:`analysis_report`."""
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
        "equivalence classes (parent SCCs): " + _sets(d["equivalence_classes"]),
        f"measured nodes: {', '.join(d['measured_nodes'])}; a minimal sensor set: "
        f"{', '.join(d['minimal_sensor_set'])}",
    ]
    if d["unmeasured_parent_sccs"]:
        lines.append("parent SCCs without sensor: " + _sets(d["unmeasured_parent_sccs"]))
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
    if not d["distributed_observable"]:
        top = max((m["abs"] for m in d["distributed_unobservable_modes"]), default=0.0)
        lines.append(
            (f"  not observable but detectable: the unobservable modes (|lambda| <= {top:.4g}) "
             "decay by themselves, so stabilising gains exist"
             + ("; but the states of a parent SCC without sensor are then estimated open "
                "loop, and `socmon design` refuses such a network (the paper's condition: "
                "let an agent measure a node of each parent SCC)"
                if d["unmeasured_parent_sccs"] else " and the estimation works"))
            if d["distributed_detectable"] else
            "  NOT DETECTABLE: an unobservable mode does not decay (|lambda| = "
            f"{top:.4g} >= 1): no gain keeps the estimation error bounded (exit 1)")
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
            txt += (f"; e.g. {_agents_words(witness)} failing "
                    + ("together " if len(witness) > 1 else "") + "is not recoverable")
            if d.get(key + "_why"):
                txt += f": {d[key + '_why']}"
        return txt

    lines += [
        f"failure tolerance (standby agents replace, no new links): {tol('failure_tolerance')}",
        f"failure tolerance with new links allowed: {tol('failure_tolerance_with_new_links')}",
        f"failure tolerance without replacement (paper's Remark 5): "
        f"{tol('failure_tolerance_without_replacement')}",
    ]
    lines += _gap_lines(d)
    for w in d["warnings"]:
        lines.append(f"warning: {w}")
    return "\n".join(lines)


def _gap_lines(d) -> list:
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
        said = gains_words(d.get("gains_meta") or {})
        lines.append(f"  with the gains of {d['gains_file']}" + (f" ({said})" if said else "")
                     + ", with the scenario's delays:")
        lines += ["  " + line for line in format_gaps(d["gaps"])]
    return lines


# -- socmon certify -------------------------------------------------------------------

def certificate_report(certified: dict, scenario, gains, gains_file) -> dict:
    """The record ``socmon certify`` prints: :func:`design.certificates.certify`'s
    (``certified``, extended in place) with the gaps (:func:`design.reports.certificate_record`),
    the gains file and its meta, and the warnings, the file's scenario mismatch (only
    with ``--force-gains``) first."""
    record = certificate_record(certified, scenario, gains.G)
    warnings = record.pop("warnings")
    mismatch = gains_scenario_mismatch(gains.meta, scenario)
    record["gains_file"] = str(gains_file)
    record["gains_meta"] = gains.meta
    record["warnings"] = ([mismatch] if mismatch is not None else []) + warnings
    return record


def format_certificates(d: dict) -> str:
    """The text of a :func:`certificate_report`."""
    said = gains_words(d.get("gains_meta") or {})
    lines = [
        f"scenario {d['scenario']}, gains {d['gains_file']}" + (f" ({said})" if said else ""),
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


# -- socmon plan ----------------------------------------------------------------------

def plan_report(scenario, failed, add_links: bool = True, write_scenario=None) -> dict:
    """The record ``socmon plan`` prints (:func:`design.reports.recovery_record`); with
    ``write_scenario`` (a path) the recovered configuration is written there as a scenario
    TOML (``scenario_written``), an InputError of status 1 when there is none."""
    plan = plan_recovery(scenario, failed, add_links=add_links)
    data = recovery_record(plan, scenario, add_links=add_links)
    if write_scenario:
        if plan.scenario_after is None:
            raise InputError(
                "--write-scenario: no recovered configuration to write (no agent left or "
                "the agent network is not strongly connected)", status=EXIT_NEGATIVE)
        path = Path(write_scenario)
        try:
            path.write_text(scenario_to_toml(plan.scenario_after))
        except OSError as exc:
            raise InputError(f"--write-scenario: cannot write {path}: {exc.strerror}") from None
        data["scenario_written"] = str(path)
    return data


def format_plan(d: dict) -> str:
    """The text of a :func:`plan_report`."""
    lines = [f"failed agents: {', '.join(map(str, d['failed']))}"]
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
    lines.append(f"agents after: {', '.join(map(str, d['agents_after']))} (rows of the new W, "
                 "in order)")
    lines.append(
        "network after removing the failed agents: "
        + ("strongly connected" if d["network_strongly_connected_removed"]
           else f"NOT strongly connected, components {d['network_components_removed']}")
    )
    if d["added_links"]:
        lines.append("links added (fewest that restore strong connectivity): "
                     + ", ".join(f"{e['from']} -> {e['to']} (agent {e['to']} listens to "
                                 f"{e['from']})" for e in d["added_links"]))
    lines.append(f"network strongly connected after: "
                 f"{_yes(d['network_strongly_connected_after'])}")
    lines.append("W after:")
    for row in d["W_after"]:
        lines.append("  " + " ".join(f"{x:6.3f}" for x in row))
    lines.append("measure after: " + "; ".join(
        f"agent {a}: {', '.join(nodes) or 'nothing'}"
        for a, nodes in zip(d["agents_after"], d["measure_after"])))
    if d.get("observability_rank_after") is not None:
        lines.append(
            f"(A, H) after: rank {d['observability_rank_after']} -> observable "
            f"{_yes(d['observable_after'])}; (W (x) A, D_H) after: rank "
            f"{d['distributed_rank_after']} of {d['distributed_order_after']}, detectable "
            f"{_yes(d['distributed_detectable_after'])}"
        )
        lines += _plan_pair_notes(d)
    if d["unmeasured_parent_sccs_after"]:
        lines.append("parent SCCs left without sensor: " + _sets(d["unmeasured_parent_sccs_after"]))
    if d.get("no_new_links"):
        lines.append("recoverable without new links: "
                     + _yes(d["recoverable_without_new_links"])
                     + ("" if d["recoverable_without_new_links"] or not d["recoverable"]
                        else " (yes if plan may add links: drop --no-new-links)"))
    else:
        lines.append("recoverable: " + _yes(d["recoverable"]))
    if "scenario_written" in d:
        lines.append(f"recovered scenario written to {d['scenario_written']}")
    return "\n".join(lines)


def _plan_pair_notes(d: dict) -> list:
    """What the rank of a plan's distributed pair means: modes that decay by themselves
    (or one that does not), and a singular W after, which costs no stability."""
    lines = []
    modes = d.get("distributed_unobservable_modes_after") or []
    top = max((m["abs"] for m in modes), default=0.0)
    if d["distributed_observable_after"] is False and d["distributed_detectable_after"]:
        lines.append(f"  not observable but detectable: the unobservable modes (|lambda| <= "
                     f"{top:.4g}) decay by themselves, so stabilising gains exist")
    elif d["distributed_detectable_after"] is False:
        lines.append(f"  NOT DETECTABLE: an unobservable mode does not decay (|lambda| = "
                     f"{top:.4g} >= 1): no gain keeps the estimation error bounded (exit 1)")
    rank, N = d.get("rank_W_after"), len(d["agents_after"])
    if rank is not None and rank < N:
        lines.append(f"  W after is singular (rank {rank} of {N}): W (x) A gets modes at 0, "
                     "which vanish in one step; the estimator never inverts W and the "
                     "certificate, the exact radius of the loop as it runs, includes them: "
                     "no stability is lost (the paper's Lemma 3 takes w_ii > 0 to make W "
                     "full rank; it need not)")
    return lines


# -- socmon design --------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class DesignRequest:
    """What one ``socmon design`` designs, parsed from its flags."""

    scenario: object
    delays: np.ndarray                # (N, N) int, designed for and certified against
    out: Path                         # the gains file to write
    method: str
    objective: str
    seed: int
    options: dict                     # keyword options of design.gain_design.design_gains
    force: bool = False               # write the file even when the gain is not stabilising


def design_request(scenario, args) -> DesignRequest:
    """The :class:`DesignRequest` of ``socmon design``'s flags ``args`` for ``scenario``;
    InputError naming the flag that is wrong or does not go with ``--method``/``--objective``
    (an existing ``--out`` file without ``--overwrite`` included, before any design)."""
    try:
        D = resolve_delays(scenario, args.delays)
    except ScenarioError as exc:
        raise InputError(str(exc)) from None
    out = Path(args.out)
    if not out.parent.is_dir():
        raise InputError(f"--out: folder {str(out.parent)!r} does not exist")
    if out.is_dir():
        raise InputError(f"--out: {str(out)!r} is a folder, give a file name")
    if (out.exists() or out.is_symlink()) and not args.overwrite:
        raise InputError(f"--out: {str(out)!r} exists: choose another file, or --overwrite "
                         "to replace it")
    objective, opts = _design_options(args)
    return DesignRequest(scenario, D, out, args.method, objective, args.seed, opts,
                         bool(args.force))


def _design_options(args) -> tuple:
    """(objective, options of design_gains) from the flags, checked together.

    >>> from argparse import Namespace
    >>> flags = dict(method="default", objective=None, target=None, solver=None,
    ...              keep_iterating=False, starts=None, no_gaps=False, window=None,
    ...              rel_tol=None, max_iter=None, time_limit=None)
    >>> _design_options(Namespace(**flags))
    ('mse', {})
    >>> _design_options(Namespace(**{**flags, "target": 0.9}))
    ('rho', {'target': 0.9, 'time_limit': 60.0})
    """
    objective = args.objective
    if objective is None:         # the one default: the gain `socmon up` designs
        objective = "rho" if args.method == "ccl" or args.target is not None else "mse"
    opts = {}
    if args.method == "ccl":
        for flag, value in (("--starts", args.starts), ("--target", args.target),
                            ("--window", args.window), ("--rel-tol", args.rel_tol),
                            ("--no-gaps", args.no_gaps or None)):
            if value is not None:
                raise InputError(f"{flag} applies to --method default only")
        if objective == "mse":
            raise InputError("--objective mse needs --method default (ccl designs for rho)")
        opts["solver"] = args.solver or "CLARABEL"
        opts["keep_iterating"] = bool(args.keep_iterating)
    else:
        if args.solver is not None:
            raise InputError("--solver applies to --method ccl only")
        if args.keep_iterating:
            raise InputError("--keep-iterating applies to --method ccl only")
        if args.starts is not None:
            opts["starts"] = args.starts
        if args.no_gaps:
            opts["gaps"] = False
        if args.window is not None:
            if args.window < 1:
                raise InputError(f"--window: must be at least 1, got {args.window}")
            opts["patience"] = args.window
        if args.rel_tol is not None:
            if not 0 <= args.rel_tol < 1:
                raise InputError(f"--rel-tol: must be in [0, 1), got {args.rel_tol}")
            opts["patience_tol"] = args.rel_tol
        if args.target is not None:
            if objective != "rho" or not 0 < args.target <= 1:
                raise InputError("--target: a radius in (0, 1] (a stabilising gain's), with "
                                 "--objective rho only")
            opts["target"] = args.target
    if args.max_iter is not None:
        if args.method == "default" and args.max_iter < 1:
            raise InputError(f"--max-iter: must be a positive integer, got {args.max_iter}")
        opts["max_iter"] = args.max_iter
    if args.time_limit is not None:
        if not args.time_limit > 0:
            raise InputError(f"--time-limit: must be positive, got {args.time_limit}")
        opts["time_limit"] = args.time_limit
    elif args.method == "default" and objective == "rho":
        opts["time_limit"] = 60.0
    return objective, opts


def design_for(request: DesignRequest, progress=None):
    """Run :func:`design.gain_design.design_gains` for ``request``: a pair that is not
    observable is an InputError of status 2, a failed conic solver one of status 1."""
    try:
        return design_gains(request.scenario, delays=request.delays, method=request.method,
                            objective=request.objective, seed=request.seed,
                            progress=progress, **request.options)
    except NotObservableError as exc:
        raise InputError(str(exc), EXIT_BAD_INPUT) from None
    except SolverError as exc:
        raise InputError(f"ccl design failed: {exc}", EXIT_NEGATIVE) from None
    except DesignError as exc:
        raise InputError(str(exc)) from None


def design_report(request: DesignRequest, res) -> dict:
    """The record ``socmon design`` prints for the :class:`~design.gain_design.DesignResult`
    ``res``; when the gain is stable (or ``--force``) the gains file is written
    (``written``) and the radius reported is that of the file as written, read back and
    computed afresh (:func:`design.reports.recheck_design`)."""
    scenario, out = request.scenario, request.out
    record = res.summary()
    record["scenario"] = scenario.name
    record["written"] = None
    if res.stable or request.force:
        meta = gains_meta(
            scenario, res.method, res.delays, res.rho, objective=res.objective,
            mse_steady_exact=res.mse_steady, stable=res.stable, seconds=res.seconds,
            iterations=res.iterations, seed=res.seed, status=res.status,
            rho_delay_free=res.rho_delay_free,
            options={k: v for k, v in res.options.items() if k != "init"},
        )
        save_gains(out, res.G, meta)
        record["written"] = str(out)
        record = recheck_design(record, scenario, request.delays, load_gains(out, scenario).G)
    return record


def design_notes(record: dict, warnings: bool = True) -> list:
    """What ``socmon design`` says on stderr of a :func:`design_report`: its warnings
    (unless ``warnings`` is false: with ``--json`` they are in the record), then whether
    no stabilising gain was found."""
    notes = [f"warning: {w}" for w in record.get("warnings", [])] if warnings else []
    if not record["stable"]:
        where = (f"written to {record['written']} (--force)" if record["written"]
                 else "no file written")
        notes.append("no stabilising gain found for these delays "
                     f"(rho = {record['rho_exact']:.6g}); {where}")
    return notes


def format_design(record: dict) -> str:
    """The text of a :func:`design_report`."""
    delays = record["delays"]
    taubar = max((max(r) for r in delays), default=0)
    free = record["rho_delay_free"]
    lines = [
        f"design {record['scenario']}: method {record['method']}, objective "
        f"{record['objective']}, for the delay matrix given (at most {taubar} steps on a "
        "link; the certificate is for these delays exactly)",
        f"  rho (exact, delays as designed for) = {record['rho_exact']:.6f}  "
        f"{'stable' if record['stable'] else 'NOT stable'}",
        f"  rho (delay-free loop)              = {free:.6f}"
        + ("" if free < 1 or not taubar else "  UNSTABLE: run this gain with the delays it "
           "was designed for (`socmon certify --taus` checks others)"),
    ]
    if record["mse_steady_exact"] is not None:
        lines.append(f"  steady MSE (exact)                 = {record['mse_steady_exact']:.6g}")
    det = record["detectability"]
    lines.append(f"  distributed pair rank {det['rank']} of {det['order']}"
                 f" ({'observable' if det['observable'] else 'detectable'})")
    lines.append(f"  {record['iterations']} iterations, {record['seconds']:.2f} s; "
                 f"stopped: {record['status']}")
    if record["status"] == "time limit":
        lines.append("  (the --time-limit budget ended the design: raise it for a lower "
                     + ("radius, or give --target RHO to stop at a radius)"
                        if record["objective"] == "rho" else "MSE)"))
    if record.get("gaps"):
        radii = ", ".join(f"{g['failed']}: {g['rho_exact']:.4f}" for g in record["gaps"])
        lines.append("  gap radii (exact; failed agent: the loop the others run until the "
                     f"switch) {radii}")
        gd = record.get("gap_design") or {}
        if gd:
            before = ", ".join(f"{f}: {r:.4f}" for f, r in gd["rho_gap_before"].items())
            lines.append(f"  gap terms (every gap below {gd['target']:.4g}): {gd['note']}"
                         + ("" if not gd["iterations"] else
                            f"; {gd['iterations']} iterations; the nominal design's gaps "
                            f"{before}"))
    if record["written"]:
        lines.append(f"  gains written to {record['written']}")
    return "\n".join(lines)

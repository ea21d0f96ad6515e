"""``socmon reproduce``: the paper's Section 5 recomputed and written to a folder.

For the pedagogical example (paper-14) and, given its edge list, Sampson's monastery:

* the table of rho against the delay bound: the paper's printed value, the paper's
  formula ``rho(Ahat)^(1/(tau+1))`` for our delay-free gain, the exact radius of that
  gain under the delay, the paper's Theorem 1 radius, and the exact radius of the gain
  designed for that delay;
* MSE figures (mean and 10-90 percentile band over the paper's number of trials): no
  failure, and for paper-14 the failure of the agents measuring 7 and 9 replaced by
  agents measuring 8 and 10 (recovery planner, gains designed for the new network);
* the steady MSE of each simulation beside the exact (Lyapunov) prediction and the
  paper's Phi (its printed value and Remark 2's formula for our gain);
* ``report.md`` saying where our numbers differ from the paper's and why, and
  ``results.json`` with every number.

Delays: for a delay bound tau every inter-agent link carries tau steps (self links 0),
the worst case of the bound.

The steps, in the order the command takes them: :func:`reproduce_options` checks the
flags and creates the output folder, :func:`run_section5` computes the records
(:func:`design.experiments.reproduce_section5`), :func:`write_reproduction` writes the
figures, the report and ``results.json``.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

from design.errors import ScenarioError
from design.experiments import PAPER, explain_failure, reproduce_section5, steady_z

from agent.run.inputs import InputError
from agent.run.jsonable import to_jsonable, versioned

__all__ = ["ReproduceOptions", "reproduce_options", "reproduce_command", "run_section5",
           "write_reproduction", "write_figures", "write_report", "differences_from_paper",
           "json_record"]


@dataclass(frozen=True)
class ReproduceOptions:
    """What ``socmon reproduce`` was asked for, checked.

    ``sampson`` is None without Sampson's edge list (Section 5.2 skipped); ``trials`` None
    means the paper's; ``command`` is the command line that gives these options, as the
    report and ``results.json`` state it.
    """

    out: Path
    steps: int
    seed: int
    trials: int | None
    objective: str
    time_limit: float | None
    sampson: str | None
    command: str


def reproduce_command(out, *, steps: int, seed: int, trials=None, objective: str = "mse",
                      time_limit=None, sampson=None) -> str:
    """The ``socmon reproduce`` command line of these flags (``out``, ``time_limit`` and
    ``sampson`` as given).

    >>> reproduce_command("repro", steps=300, seed=0)
    'socmon reproduce --out repro --steps 300 --seed 0 --objective mse'
    >>> reproduce_command("r", steps=60, seed=1, trials=4, time_limit="30")
    'socmon reproduce --out r --steps 60 --seed 1 --trials 4 --objective mse --time-limit 30'
    """
    return "socmon reproduce" \
        + (f" --sampson {sampson}" if sampson else "") \
        + f" --out {out} --steps {steps} --seed {seed}" \
        + (f" --trials {trials}" if trials else "") + f" --objective {objective}" \
        + (f" --time-limit {time_limit}" if time_limit is not None else "")


def reproduce_options(out, *, steps: int, seed: int, trials=None, objective: str = "mse",
                      time_limit=None, sampson=None) -> ReproduceOptions:
    """Check the flags not checked yet and create the folder ``out``.

    ``out``, ``time_limit`` (seconds) and ``sampson`` (a path) are the texts given;
    ``steps``, ``seed`` and ``trials`` are already checked integers. An
    :class:`~agent.run.inputs.InputError` (exit 2) names the first bad flag, in the
    order ``--time-limit``, ``--sampson``, ``--out``.

    >>> reproduce_options("out", steps=300, seed=0, time_limit="0")
    Traceback (most recent call last):
    ...
    agent.run.inputs.InputError: --time-limit: expected a positive number of seconds, got '0'
    """
    seconds = None
    if time_limit is not None:
        try:
            seconds = float(time_limit)
        except ValueError:
            seconds = -1.0
        if not seconds > 0:
            raise InputError(f"--time-limit: expected a positive number of seconds, got "
                             f"{time_limit!r}")
    if sampson and not Path(sampson).is_file():
        raise InputError(f"--sampson: no such file {str(sampson)!r}")
    folder = Path(out)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"--out: cannot create {str(folder)!r}: {exc.strerror}") from None
    command = reproduce_command(out, steps=steps, seed=seed, trials=trials,
                                objective=objective, time_limit=time_limit, sampson=sampson)
    return ReproduceOptions(out=folder, steps=steps, seed=seed, trials=trials,
                            objective=objective, time_limit=seconds,
                            sampson=sampson or None, command=command)


def run_section5(options: ReproduceOptions, log=None, progress=None,
                 sim_progress=None) -> dict:
    """The records of :func:`design.experiments.reproduce_section5` for ``options``, with
    ``"command"``; ``log``, ``progress`` and ``sim_progress`` are passed on. A bad Sampson
    file is an :class:`~agent.run.inputs.InputError` naming ``--sampson``."""
    try:
        results = reproduce_section5(steps=options.steps, seed=options.seed,
                                     trials=options.trials, objective=options.objective,
                                     time_limit=options.time_limit,
                                     sampson_path=options.sampson, log=log,
                                     progress=progress, sim_progress=sim_progress)
    except ScenarioError as exc:
        raise InputError(f"--sampson: {exc}") from None
    results["command"] = options.command
    return results


def write_reproduction(out: Path, results: dict, plot_mse) -> Path:
    """Write the MSE figures (drawn by ``plot_mse``, see :func:`write_figures`),
    ``report.md`` and ``results.json`` of ``results`` into ``out``; the report's path."""
    write_figures(out, results, plot_mse)
    report = write_report(out, results)
    (out / "results.json").write_text(
        json.dumps(to_jsonable(versioned(json_record(results))), indent=1) + "\n")
    return report


def write_figures(out: Path, results: dict, plot_mse) -> None:
    """The MSE figures of every record (names stored in the records as ``figure``).

    ``plot_mse(path, curves, title=..., events=...)`` writes one figure
    (``agent.cli._plot.plot_mse``).
    """
    for key in ("paper-14", "sampson"):
        r = results.get(key)
        if r is None:
            continue
        r["figure"] = f"{r['scenario']}-mse.png"
        plot_mse(out / r["figure"], r["curves"], title=f"{r['scenario']}: MSE, "
                 f"{r['trials']} trials, delay bound tau (every link)")
        f = r.get("failure")
        if f and "curves" in f:
            f["figure"] = f"{r['scenario']}-failure-mse.png"
            plot_mse(out / f["figure"], f["curves"],
                     title=f"{r['scenario']}: agents measuring {', '.join(f['failed_nodes'])} "
                           f"fail at step {f['fail_step']}",
                     events=[(f["fail_step"], "failure / recovery")])


def json_record(obj):
    """``obj`` without its Scenario and SimulationResult objects (keys ``new_scenario``
    and ``curves``), as ``results.json`` holds it.

    >>> json_record({"paper-14": {"rho_A": 1.2, "curves": [], "failure": [{"new_scenario": 0}]}})
    {'paper-14': {'rho_A': 1.2, 'failure': [{}]}}
    """
    if isinstance(obj, dict):
        return {k: json_record(v) for k, v in obj.items() if k not in ("new_scenario", "curves")}
    if isinstance(obj, list):
        return [json_record(v) for v in obj]
    return obj


# ---------------------------------------------------------------------------------
# report


def _number(x, d=4):
    """A number of the report: ``d`` decimals, small ones in scientific notation.

    >>> _number(0.87123), _number(0.87123, 3), _number(2.5e-5), _number(None), _number(math.inf)
    ('0.8712', '0.871', '2.50e-05', '-', 'inf')
    """
    if x is None:
        return "-"
    if isinstance(x, float) and not math.isfinite(x):
        return "inf"
    return f"{x:.{d}f}" if abs(x) >= 1e-3 or x == 0 else f"{x:.2e}"


def _rho_section(title, rows, with_theorem=True):
    head = ("| tau | paper | paper's formula, our delay-free gain | exact, our delay-free gain |"
            + (" Theorem 1 rho, delay-free gain |" if with_theorem else "")
            + " exact, gain designed for tau |")
    sep = "|---" * (head.count("|") - 1) + "|"
    lines = [f"### {title}", "", head, sep]
    for r in rows:
        lines.append(
            f"| {r['tau']} | {_number(r['paper'], 3)} | {_number(r['paper_formula_ours'])} | "
            f"{_number(r['exact_delay_free_gain'])} |"
            + (f" {_number(r['theorem1_delay_free_gain'])} |" if with_theorem else "")
            + f" {_number(r['exact_designed_gain'])} |")
    return lines


def _mse_section(title, sims, paper_phi, our_phi):
    lines = [f"### {title}", "",
             "| tau | exact radius | simulated steady MSE (± s.e.) | exact steady MSE (Lyapunov) |"
             " \\|sim - exact\\| / s.e. | paper's Phi | Phi (Remark 2) for our gain |",
             "|---|---|---|---|---|---|---|"]
    for i, s in enumerate(sims):
        se = s["mse_steady_se"]
        sim = _number(s["mse_steady"]) + (f" ± {_number(se)}" if se is not None else "")
        if s["diverged"]:
            sim += " (diverged)"
        z = steady_z(s)
        lines.append(
            f"| {s['tau']} | {_number(s['rho_exact'])} | {sim} | "
            f"{_number(s['mse_steady_exact'])} | "
            f"{'-' if z is None else f'{z:.1f}'} | "
            f"{_number(paper_phi, 3) if i == 0 else '-'} | "
            f"{_number(our_phi.get('phi')) if i == 0 else '-'} |")
    return lines


def write_report(out: Path, results: dict) -> Path:
    """Write ``report.md`` of ``results`` (figure names set by :func:`write_figures`) into
    ``out``; its path."""
    L = ["# The paper's Section 5, recomputed by socmon", "",
         f"Command: `{results['command']}`. Every figure below is recomputed; "
         f"`results.json` has all numbers, per-step MSE included.", "",
         "Conventions: A of the pedagogical example is the transpose of the printed matrix "
         "(docs and NOTES section 1); for a delay bound tau every inter-agent link is delayed "
         "tau steps, the worst case of the bound, self links undelayed; MSE = mean over "
         "agents and states of e^2; simulated steady MSE = mean over the last quarter of "
         "the steps, ± its standard error across trials. Gains: `design_gains` with "
         f"objective `{results.get('objective', 'rho')}` for each network and delay "
         "bound, each started from the neighbouring design and certified by the exact "
         "radius of its delayed loop.", ""]
    for key, title in (("paper-14", "Pedagogical example (Section 5.1)"),
                       ("sampson", "Sampson's monastery (Section 5.2)")):
        if key not in results:
            continue
        r = results[key]
        L += [f"## {title}", "",
              f"n = {r['n']}, N = {r['N']}, rho(A) = {r['rho_A']:.4f}; {r['trials']} trials x "
              f"{r['steps']} steps, seed {r['seed']}.", ""]
        L += _rho_section("Spectral radius against the delay bound", r["rho_table"])
        L += ["", f"![MSE]({r['figure']})", ""]
        L += _mse_section("Steady MSE", r["simulations"], r["paper_phi"],
                          r["phi_delay_free_gain"])
        L.append("")
        if "failure" in r:
            f = r["failure"]
            L += [f"### Failure of the agents measuring {', '.join(f['failed_nodes'])} "
                  f"(agents {f['failed_agents']}) at step {f['fail_step']}", "",
                  f"Recovery planner: replacement nodes {f.get('replacement_nodes')}; agents "
                  f"after: {f.get('agents_after')} measuring {f.get('measure_after')}. "
                  "Replacement agents take over the failed agents' last estimates and the "
                  "gains designed for the new network.", ""]
            if "rho_table" in f:
                L += _rho_section("Recovered network: spectral radius", f["rho_table"],
                                  with_theorem=False)
                L += ["", f"![MSE with failure]({f['figure']})", ""]
                L += _mse_section("Recovered network: steady MSE", f["simulations"],
                                  PAPER["paper-14-recovered"]["phi"],
                                  f.get("phi_delay_free_gain", {}))
                nr = f["no_recovery"]
                rad = f.get("unmeasured_parent_radius")
                L += ["", f"Without recovery (tau = {nr['tau']}): steady MSE "
                      f"{_number(nr['mse_steady'])}"
                      + (" (diverged)" if nr["diverged"] else "")
                      + ", the mean over the agents still running (their own gains, the "
                      "failed neighbours' weights on themselves)."
                      + ("" if rad is None else
                         f" The parent SCCs left unmeasured have spectral radius {rad:.4f}"
                         + (" < 1: the survivors' pair stays detectable, so their error "
                            "can stay bounded without recovery; recovery restores "
                            "observability." if rad < 1 else
                            " >= 1: without recovery the error cannot stay bounded.")), ""]
        if r["problems"]:
            L += ["Problems: " + "; ".join(r["problems"]), ""]
    why = explain_failure(results)
    if why:
        L += ["## What the failure figure shows, and why", ""] + why + [""]
    L += ["## Where our numbers differ from the paper's, and why", ""]
    L += differences_from_paper(results)
    path = out / "report.md"
    path.write_text("\n".join(L) + "\n")
    return path


def _mse_statement(name, sim, paper_phi, our_phi, note) -> str:
    exact = sim["mse_steady_exact"]
    ratio = f" ({exact / paper_phi:.2g} times the paper's Phi)" if exact else ""
    phi_text = _number(our_phi) if our_phi is not None else f"undefined ({note})"
    return (
        f"- **Steady MSE against Phi ({name}, delay-free).** The paper's Phi is {paper_phi}; "
        f"for our gain the exact steady MSE (Lyapunov) is {_number(exact)}{ratio}, the "
        f"simulation gives {_number(sim['mse_steady'])}, and Remark 2's Phi for our gain is "
        f"{phi_text}. Phi is an approximation with an unspecified beta, neither a bound nor "
        "an exact value, and depends on the gain; the Lyapunov value is exact for our gain"
        + _agreement(sim) + ".")


def _agreement(sim) -> str:
    exact, got, se = sim["mse_steady_exact"], sim["mse_steady"], sim["mse_steady_se"]
    if exact is None or se is None:
        return ""
    z = abs(got - exact) / se if se > 0 else math.inf
    if z <= 3:
        return f"; the simulated value is within {z:.1f} standard errors of it"
    return (f"; the simulated value is {z:.1f} standard errors away from it (the run may be "
            "too short for the transient to die out)")


def differences_from_paper(results) -> list:
    """Plain statements comparing our numbers with the paper's."""
    out = []
    p = results.get("paper-14")
    if p:
        row0 = p["rho_table"][0]
        out.append(
            f"- **Delay-free radius.** The paper reports rho(Ahat) = {row0['paper']:.3f} for "
            f"paper-14; our designed gain gives {row0['exact_designed_gain']:.4f}. The "
            "printed gains are rounded and the cycle weights are not given, so they cannot "
            "be reused; any stabilising design gives a different radius.")
        worst = max(p["rho_table"], key=lambda r: r["tau"])
        out.append(
            f"- **The tables for tau > 0 are the paper's formula, not a certificate.** The "
            f"paper's values equal rho(Ahat)^(1/(tau+1)) (ours: {worst['paper_formula_ours']:.4f} "
            f"at tau = {worst['tau']}, paper {worst['paper']:.3f}). The exact radius of the "
            f"delayed closed loop for our delay-free gain is "
            f"{worst['exact_delay_free_gain']:.4f} at tau = {worst['tau']}"
            + (" (UNSTABLE)" if worst["exact_delay_free_gain"] >= 1 else "")
            + ": delays can destabilise a delay-free design (NOTES section 3; with "
            "rho(A) > 1 as here, and with a stable A too), contrary to the claim that "
            "the gain works irrespective of the delays. A gain designed for the delay gives "
            f"{worst['exact_designed_gain']:.4f}.")
        unstable = [r["tau"] for r in p["rho_table"] if r["exact_delay_free_gain"] >= 1]
        if unstable:
            out.append(f"- Our delay-free gain is unstable under delays tau = {unstable}; "
                       "the MSE figures therefore use, for each tau, the gain designed for it.")
        s0 = p["simulations"][0]
        phi = p["phi_delay_free_gain"].get("phi")
        out.append(_mse_statement("paper-14", s0, p["paper_phi"], phi,
                                  p["phi_delay_free_gain"].get("phi_note", "")))
        f = p.get("failure")
        if f and "rho_table" in f:
            out.append(
                f"- **Recovery.** The planner replaces the measurements of "
                f"{f['failed_nodes']} by {f.get('replacement_nodes')} (paper: 8 and 10); "
                f"recovered delay-free radius {f['rho_table'][0]['exact_designed_gain']:.4f} "
                f"(paper 0.851).")
        out.append(
            "- **Observability.** The distributed pair (W (x) A, D_H) of paper-14 is not "
            "observable (numerical rank 33 of 42: nodes 6..14 have a_ii = 0); its "
            "unobservable modes are stable, so it is detectable and stabilising gains exist.")
    slow = []
    for key in ("paper-14", "sampson"):
        r = results.get(key)
        if not r:
            continue
        for label, sims in ((key, r["simulations"]),
                            (key + " recovered", r.get("failure", {}).get("simulations", []))):
            for sim in sims:
                z = steady_z(sim)
                if z is not None and z > 3:
                    slow.append(f"{label} tau = {sim['tau']} (radius {sim['rho_exact']:.4f})")
    if slow:
        out.append(
            "- **Runs too short for slow loops.** The simulated steady MSE is more than 3 "
            "standard errors from the exact value for " + ", ".join(slow) + ": with a "
            "radius near 1 the transient decays like radius^k and has not died out within "
            "the run (the band in the figure shows it); use more `--steps`. The exact "
            "value is the steady state.")
    s = results.get("sampson")
    if s:
        row0, last = s["rho_table"][0], s["rho_table"][-1]
        out.append(
            f"- **Sampson.** The paper's random weights are not published; ours are drawn "
            f"from seed {s.get('weights_seed', 0)} and rescaled to rho(A) = 1.1, so A and "
            f"every number differ: delay-free radius {row0['exact_designed_gain']:.4f} "
            f"(paper {row0['paper']:.3f}); at tau = {last['tau']} the paper's formula gives "
            f"{last['paper_formula_ours']:.4f} (paper {last['paper']:.3f}), the exact radius "
            f"of our delay-free gain is {last['exact_delay_free_gain']:.4f}"
            + (" (UNSTABLE)" if last["exact_delay_free_gain"] >= 1 else "")
            + f" and that of the gain designed for it {last['exact_designed_gain']:.4f}.")
        phi = s["phi_delay_free_gain"].get("phi")
        out.append(_mse_statement("sampson", s["simulations"][0], s["paper_phi"], phi,
                                  s["phi_delay_free_gain"].get("phi_note", "")))
    if not out:
        out.append("- (no experiment run)")
    return out

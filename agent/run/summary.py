"""The summary of a local run: pure functions of its :class:`agent.run.local.Recording`.

MSE per step over the agents in force at that step (the roster), failures and
recoveries from the monitor's record (``events.jsonl``) and the assignments heard, the
exact prediction for every configuration, the comparison with the simulator's replay,
and the run folder's files.
"""

from __future__ import annotations

import io
import math
import time
from pathlib import Path

import numpy as np

from design.metrics import (BATCHES, batch_means_se, mean_recorded, mse_of_step,
                            steady_mse, steady_window)

__all__ = ["run_and_summarize", "predicted_mse", "failure_lines", "final_roles", "summarize", "mse_by_step", "specs_in_force", "rosters_in_force", "switch_steps", "compare_simulator", "period_warning", "was_compared", "links_impaired", "impairments_at",
           "write_run_folder", "save_estimates", "CHECK_TOL", "VERDICT_SLACK_S",
           "conviction_bound_s", "no_verdict_due"]

#: --check-simulator passes when the estimates agree to this (relative, see docs/runtime.md)
CHECK_TOL = 1e-9
#: A run recovered when the steady MSE after its last switch is within this factor of the
#: exact prediction for the configuration in force.
RECOVERED_FACTOR = 3.0
#: A run diverged at the first step whose MSE is not finite or above this factor times
#: the larger exact prediction (the configuration started with, the one in force at the
#: end); with no finite prediction, only a non-finite MSE counts.
DIVERGED_FACTOR = 1e3
#: Scheduling slack (s) beyond a stop's verdict time before a verdict is required of the
#: monitor (chaos's ``recovery`` invariant; the summary's ``no_verdict_due``).
VERDICT_SLACK_S = 0.3


def conviction_bound_s(kind: str, hang_timeout_s: float, step_s: float,
                       max_delay: int) -> float | None:
    """How long a fault of ``kind`` must last before the monitor must have convicted its
    agent (seconds; None: a kind whose length decides no verdict). The rules are the
    detector's (docs/monitor.md, *Detection*): a ``stop`` is convicted once the agent's
    last status, up to a status period before the stop, is a hang timeout old (plus
    :data:`VERDICT_SLACK_S` for scheduling); a ``partition`` or ``sensor`` cut once the
    listeners' ages (or the reading's lag) pass ``silent_steps`` plus the largest link
    delay, and then the hang timeout, with a hang timeout of margin.

    >>> conviction_bound_s("stop", 1.0, 0.02, 3)
    1.5
    >>> round(conviction_bound_s("partition", 1.0, 0.02, 3), 6)
    2.56
    >>> conviction_bound_s("drop", 1.0, 0.02, 3) is None
    True
    """
    from agent.monitor.core import MonitorConfig
    from agent.protocol.timing import DEFAULT as TIMING

    if kind == "stop":
        return hang_timeout_s + TIMING.status_s + VERDICT_SLACK_S
    if kind in ("partition", "sensor"):
        return 2 * hang_timeout_s + (MonitorConfig.silent_steps + int(max_delay)) * step_s
    return None


def no_verdict_due(faults, failures, hang_timeout_s: float, step_s: float,
                   max_delay: int) -> list:
    """The faults of a run that drew no verdict because none was due: a ``stop``,
    ``partition`` or ``sensor`` cut not longer than its :func:`conviction_bound_s`, with no
    verdict about its agent from its step until that agent's next fault. Each is
    ``{"fault": Fault.to_dict(), "why": words}``.

    >>> from agent.run.local import Fault
    >>> [d["why"] for d in no_verdict_due([Fault(150, "stop", 3, 0.5)], [], 1.0, 0.02, 0)]
    ['stop of agent 3 for 0.5 s at step 150: no verdict, and none was due: not longer than the hang timeout (1 s) plus a status period (0.2 s) and a margin (0.3 s)']
    """
    out = []
    for f in faults:
        bound = conviction_bound_s(f.kind, hang_timeout_s, step_s, max_delay)
        if bound is None or f.seconds > bound:
            continue
        until = min((g.step for g in faults if g.agent == f.agent and g.step > f.step),
                    default=math.inf)
        if any(v.get("agent") == f.agent and v.get("detected_step") is not None
               and f.step <= v["detected_step"] < until for v in failures):
            continue
        if f.kind == "stop":
            from agent.protocol.timing import DEFAULT as TIMING

            rule = (f"the hang timeout ({hang_timeout_s:g} s) plus a status period "
                    f"({TIMING.status_s:g} s) and a margin ({VERDICT_SLACK_S:g} s)")
        else:
            from agent.monitor.core import MonitorConfig

            rule = (f"twice the hang timeout ({hang_timeout_s:g} s) plus "
                    f"{MonitorConfig.silent_steps} steps and the largest link delay "
                    f"({int(max_delay)} steps), {bound:.3g} s in all")
        what = {"stop": "stop", "partition": "partition", "sensor": "sensor cut"}[f.kind]
        out.append({"fault": f.to_dict(),
                    "why": f"{what} of agent {f.agent} for {f.seconds:g} s at step {f.step}: "
                           f"no verdict, and none was due: not longer than {rule}"})
    return out


def diverged_at(steps, mse, predictions) -> int | None:
    """The first step whose MSE is not finite or exceeds :data:`DIVERGED_FACTOR` times the
    largest finite value of ``predictions``; None when there is none.

    >>> diverged_at([0, 1, 2, 3], [0.3, 0.5, 500.0, float("inf")], [0.27, 0.4])
    2
    >>> diverged_at([0, 1], [0.3, 0.5], [float("inf")]) is None
    True
    """
    finite = [p for p in predictions if p is not None and math.isfinite(p)]
    bound = DIVERGED_FACTOR * max(finite) if finite else math.inf
    for k, m in zip(steps, mse):
        if not math.isfinite(m) or m > bound:
            return int(k)
    return None


def record_gaps(steps, record_every: int, last_step: int) -> list:
    """``[[first, last], ...]``: the runs of kept steps (:func:`agent.run.recorder.kept_step`)
    between the first and the last recorded one (:func:`mse_by_step`) that the record
    lacks: the recorder did not receive their truth or any estimate of them (it was
    paused or cut off while the processes ran them), or no agent in force published one.

    >>> record_gaps([0, 1, 2, 6, 7, 9], 1, 9)
    [[3, 5], [8, 8]]
    >>> record_gaps([0, 10, 30, 35], 10, 35)
    [[20, 20]]
    """
    from agent.run.recorder import kept_step

    if not len(steps):
        return []
    held, gaps, in_gap = set(steps), [], False
    for k in range(int(steps[0]), int(steps[-1]) + 1):
        if not kept_step(k, record_every, last_step):
            continue
        if k in held:
            in_gap = False
        elif in_gap:
            gaps[-1][1] = k
        else:
            gaps.append([k, k])
            in_gap = True
    return gaps


def mse_by_step(rec, K, rosters=None):
    """``(steps, mse)``: mean over the agents in force at each step (``rosters``, default
    :func:`rosters_in_force` of the recording), over the steps whose truth and an estimate
    of an agent in force were recorded (a step without either is a gap of the record,
    :func:`record_gaps`, not an error of the estimates)."""
    if rosters is None:
        rosters = rosters_in_force(rec.rosters, rec.est_epoch, rec.assigns)[0]

    def in_force(k):
        return [ids for at, ids, _ in rosters if at <= k][-1]

    steps, mse = [], []
    for k in sorted(k for k in rec.truth if k <= K):
        m = mse_of_step([rec.est[a][k] for a in in_force(k) if k in rec.est[a]], rec.truth[k])
        if m is not None:
            steps.append(k)
            mse.append(m)
    return steps, np.array(mse, dtype=float)


def run_and_summarize(config, say=lambda text: None) -> tuple:
    """Run ``config`` live (:class:`agent.run.local.LocalRun`) and summarize it:
    ``(rec, summary, steps, mse, predicted)``, ``predicted`` the exact steady MSE of the
    configuration started with (inf when its loop is not stable)."""
    from agent.run.local import LocalRun

    rho, predicted = predicted_mse(config.scenario, config.G, config.delays)
    rec = LocalRun(config, say).run()
    summary, steps, mse = summarize(config, rec, rho, predicted)
    return rec, summary, steps, mse, predicted


def predicted_mse(scenario, G, delays) -> tuple:
    """``(rho, mse_steady)`` of the exact closed loop of ``G`` (mse inf when there is none,
    :func:`design.closed_loop.exact_performance`)."""
    from design.closed_loop import exact_performance

    p = exact_performance(scenario, G, delays)
    return p.rho, p.mse_or_inf


def summarize(config, rec, loop_rho, predicted) -> tuple:
    """``(summary, steps, mse)`` of a run (see docs/runtime.md and docs/monitor.md); pure:
    the run folder is written by :func:`write_run_folder`."""
    from agent.run.jsonable import SCHEMA_VERSION

    c = config
    K, N, M = c.steps, c.scenario.N, c.M
    if rec.complete_step is not None:      # interrupted: the steps every agent published
        K = min(K, rec.complete_step)
    steps, mse = mse_by_step(rec, K)
    # the last quarter of the run's K steps (by position: a watcher that attached late
    # averages the same final steps as the run's own recorder), or of the steps run when
    # it ended early (interrupted: not its start-up transient); of the recorded ones
    tail = -(-steady_window(min(K, steps[-1]) if steps else K) // c.record_every)
    mse_steady = mean_recorded(mse[-tail:])
    window = [int(steps[-tail:][0]), int(steps[-1])] if steps else None
    last = {a: rec.status.get(a, {}) for a in range(1, M + 1)}
    children = rec.children.children.values() if rec.children is not None else ()
    summary = {
        "schema_version": SCHEMA_VERSION,
        "scenario": c.scenario.name,
        "run": rec.run_id,
        "ports": rec.ports,
        "seed": c.seed,
        "steps": int(steps[-1]) if steps else -1,
        "steps_requested": c.steps,
        "record_every": c.record_every,
        "step_ms": c.step_ms,
        "deadline_ms": c.deadline_ms,
        "agents": N,
        "standby": c.scenario.standby,
        "delays_spec": c.delays_spec,
        "delays": np.asarray(c.delays).tolist(),
        "drop": c.drop,
        "rho_exact": loop_rho,
        "mse_steady": mse_steady,
        # its standard error by batch means, and the steps it covers (the last quarter)
        "mse_steady_se": batch_means_se(mse[-tail:]),
        "mse_steady_window": window,
        "mse_steady_exact": predicted,
        "drops": sum(s.get("drops", 0) for s in last.values()),
        "late": sum(s.get("late", 0) for s in last.values()),
        "malformed": sum(s.get("malformed", 0) for s in last.values()),
        "fenced": sum(s.get("fenced", 0) for s in last.values()),
        "recorder_malformed": rec.recorder_malformed,
        "sensor_missed": sum(s.get("sensor", {}).get("missed", 0) for s in last.values()),
        "sensor_future": sum(s.get("sensor", {}).get("future", 0) for s in last.values()),
        "implausible": {kind: sum(s.get("implausible", {}).get(kind, 0) for s in last.values())
                        for kind in ("estimates", "readings")},
        "learned_delays": {str(a): {str(j): d for j, d in s.get("delays", {}).items()}
                           for a, s in last.items() if s},
        "hop_ms": {str(a): s.get("hop_ms") for a, s in last.items() if s.get("hop_ms")},
        # whose estimates each agent subscribed to last, and how many it got from each
        "estimates_from": {str(a): s["estimates_from"] for a, s in last.items()
                           if s.get("estimates_from")},
        "cpu_s": {ch.name: ch.cpu_s for ch in children},
        "wall_s": rec.wall,
        "exit_status": {ch.name: ch.returncode for ch in children},
        "orphans": [ch.name for ch in children if ch.returncode is None],
        "monitor": c.monitor,
        "world_silent": rec.world_silent,
        "faults": [dict(f.to_dict(), **({"note": note} if note else {}))
                   for f in c.faults for note in [f.standby_note(c.scenario.N)]],
        "events": rec.events,
        "final_roles": final_roles(last, rec.events, steps[-1] if steps else -1),
    }
    summary.update(_failures(c.out / "events.jsonl" if c.out is not None else None, rec,
                             c.scenario, c.delays, steps, mse, c.G))
    if c.monitor and c.faults and c.step_ms:
        from design.roster import link_delay_table

        summary["no_verdict_due"] = no_verdict_due(   # of the faults the run reached
            [f for f in c.faults if steps and f.step <= steps[-1]],
            summary.get("failures", []), c.hang_timeout, c.step_ms / 1000.0,
            int(link_delay_table(c.scenario, c.delays).max()))
    warnings = []
    # the prediction for what was in force over the steady window (the last quarter)
    window_from = steps[-tail] if len(steps) >= tail else (steps[0] if steps else 0)
    last_switch = summary["rosters"][-1]["activate_at"] if len(summary["rosters"]) > 1 else 0
    summary["mse_steady_exact_in_force"] = (
        summary.get("mse_steady_exact_after_recovery") if last_switch
        and last_switch <= window_from else predicted if not last_switch else None)
    if last_switch and last_switch > window_from and "roles_unheard_before" not in summary:
        warnings.append(f"the steady window (from step {window_from}) begins before the last "
                        f"switch (step {last_switch}): no single exact prediction covers it")
    summary["diverged_at"] = diverged_at(
        steps, mse, [predicted, summary.get("mse_steady_exact_after_recovery")])
    if summary["diverged_at"] is not None:
        warnings.append(f"the estimates DIVERGED: the MSE at step {summary['diverged_at']} "
                        f"is above {DIVERGED_FACTOR:g}x every exact prediction (or not finite)")
    impaired = links_impaired(rec.events, c.scenario, c.delays)
    if impaired:        # the predictions know the run's delays, not what was injected
        warnings.append(
            f"links were impaired during the run (from step {impaired[0][0]}, into agent "
            f"{impaired[0][1]}: a link fault or socmon inject): the exact predictions assume "
            "the run's own delays only")
    late = period_warning(last, faulty=bool(summary.get("failures") or c.faults))
    if late:
        warnings.append(late)
    gaps = summary["record_gaps"] = record_gaps(steps, c.record_every, K)
    if gaps:
        warnings.append(
            "the record misses steps "
            + ", ".join(f"{a}-{b}" if b > a else f"{a}" for a, b in gaps[:5])
            + (" ..." if len(gaps) > 5 else "")
            + ": the recorder did not receive their truth or any estimate of them (it was "
            "paused or cut off while the processes ran them), or no agent in force "
            "published one; the MSE and its figures leave them out")
    summary["warnings"] = summary.get("warnings", []) + warnings
    logged = log_warnings(c.out / "logs") if c.out is not None else []
    summary["warnings"] = list(dict.fromkeys(list(c.scenario.warnings) + logged
                                             + summary.get("warnings", [])))
    return summary, steps, mse


def final_roles(last_status, events, last_step) -> dict:
    """``final_roles`` of a summary: each agent's last status (``epoch``, ``measure``)
    and whether it ended ``dead`` (its process exited during the run, or its liveliness
    token went before the last step), ``fenced`` (alive, it dropped its role: convicted
    by the monitor) and ``active`` (it held a role at the end: its last status said so
    and it is neither dead nor fenced).

    >>> st = {1: {"active": True, "epoch": 0, "measure": ["a"]},
    ...       2: {"active": False, "epoch": 1, "measure": []}}
    >>> ev = [{"process": "agent-1", "exit_status": -9, "step": 150},
    ...       {"process": "agent-2", "role": "dropped", "epoch": 1, "step": 90}]
    >>> r = final_roles(st, ev, 400)
    >>> r["1"]["dead"], r["1"]["active"], r["2"]["fenced"], r["2"]["dead"]
    (True, False, True, False)
    """
    dead, fenced = set(), set()
    for e in events:
        name = e.get("process", "")
        if not name.startswith("agent-") or not name[6:].isdigit():
            continue
        a = int(name[6:])
        step = e.get("step")
        if e.get("exit_status") is not None or (
                e.get("liveliness") is False and isinstance(step, int) and step < last_step):
            dead.add(a)
        elif e.get("role") == "dropped":
            fenced.add(a)
    out = {}
    for a, st in last_status.items():
        if not st:
            continue
        out[str(a)] = {"active": bool(st.get("active")) and a not in dead and a not in fenced,
                       "epoch": st.get("epoch"), "measure": st.get("measure"),
                       "dead": a in dead, "fenced": a in fenced and a not in dead}
    return out


def period_warning(last_statuses: dict, faulty: bool) -> str | None:
    """The warning that the step period was not sustained, from the agents' last statuses
    (agent -> status), or None: more than 1 % of the neighbour estimates their steps used
    (``inputs``) missed the step that needed them. An agent counts such an estimate in
    ``drops`` when it computes without it, and again in ``late`` when it comes after, so
    ``drops`` holds the late ones; with faults (``faulty``: a failed agent's missing
    estimates are drops too) only the late ones count.

    >>> period_warning({1: {"inputs": {"fresh": 90, "held": 10}, "drops": 6, "late": 4}},
    ...                faulty=False)
    'period not sustained: 6 of 100 neighbour estimates (6.0 %) were late or dropped (the machine is too loaded for this step period, or links are impaired)'
    """
    statuses = [s for s in last_statuses.values() if s]
    needed = sum(sum((s.get("inputs") or {}).values()) for s in statuses)
    missed = sum(s.get("late" if faulty else "drops", 0) for s in statuses)
    if not needed or not missed > 0.01 * needed:
        return None
    return (f"period not sustained: {missed} of {needed} neighbour estimates "
            f"({100 * missed / needed:.1f} %) were " + ("late" if faulty else "late or dropped")
            + " (the machine is too loaded for this step period, or links are impaired)")


def headline_lines(summary: dict, scenario) -> list:
    """The lines ``socmon up`` prints of a finished run: the MSE against its prediction for
    the configuration in force, the message counts, each failure, the run folder."""
    if summary["steps"] < 0:         # why: the error said after these lines
        return [f"{scenario.name}: no step recorded", f"run folder: {summary['out']}"]
    exact = summary.get("mse_steady_exact_in_force")
    rosters = summary.get("rosters") or []
    now = len(rosters[-1]["ids"]) if rosters else scenario.N
    first = (f"{scenario.name}: {summary['steps']} steps, {scenario.N} agents"
             + (f" ({now} in force at the end)" if now != scenario.N else "") + ", mse_steady "
             f"{steady_text(summary, 'mse_steady')} (predicted "
             + (f"{exact:.4g} for the configuration in force" if exact is not None
                else prediction_missing(summary))
             + (f"; DIVERGED at step {summary['diverged_at']}"
                if summary.get("diverged_at") is not None else "") + "), drops "
             f"{summary['drops']}, late {summary['late']}, malformed {summary['malformed']}"
             + (f", max_rel_diff_vs_simulator {summary['max_rel_diff_vs_simulator']:.3g}"
                if "max_rel_diff_vs_simulator" in summary else ""))
    return [first, *failure_lines(summary), f"run folder: {summary['out']}"]


def prediction_missing(summary) -> str:
    """Why a summary has no exact prediction for its steady window, in a few words."""
    if "roles_unheard_before" in summary:
        return "n/a: the roles in force were assigned before the record began"
    if summary.get("mse_steady_exact") is None:
        return "n/a: no gains given"
    return "n/a: the window spans a switch"


def failure_lines(summary) -> list:
    """One line per failure of a summary (and the MSE after recovery), for terminals."""
    lines = []
    for f in summary.get("failures", []):
        if f.get("detected") is False:
            lines.append(f"  failure: agent {f['agent']} died at step {f['died_step']} and was "
                         f"never convicted ({f['why']}): "
                         + ("a standby, it held no role" if f.get("role") == "standby"
                            else "not recovered"))
            continue
        rep = f.get("replacement") or {}
        measures = rep.get("measures") or [rep.get("node")]
        links = f.get("added_links") or []
        lines.append(f"  failure: agent {f['agent']} {f['cause']} at step {f['detected_step']}"
                     + (f"; agent {rep.get('agent')} measures "
                        + (" and ".join(map(str, measures)) if len(measures) <= 2
                           else ", ".join(map(str, measures[:-1])) + f" and {measures[-1]}")
                        + (f" (node {rep.get('node')} new)" if len(measures) > 1 else "")
                        + f" from step {f.get('activate_at')}" if rep else "")
                     + ("; link" + ("s" if len(links) > 1 else "") + " added: "
                        + ", ".join(f"{e['to']} listens to {e['from']}" for e in links)
                        if links else "")
                     + (f" (links impaired then: {', '.join(f['links_impaired'])})"
                        if f.get("links_impaired") else ""))
    lines += [f"  {d['why']}" for d in summary.get("no_verdict_due", [])]
    lines += [f"  rejoined: agent {r['agent']} at step {r['step']}, healthy "
              f"{r.get('healthy_s') or 0:g} s on probation" for r in summary.get("rejoins", [])]
    lines += [f"  residual alert: agent {a['agent']} {a['fault']} at step {a['step']}"
              + (f" (level {a['score']:.3g})" if isinstance(a.get("score"), (int, float))
                 else "") for a in summary.get("residual_alerts", [])]
    if summary.get("evidence_refused"):
        lines.append(f"  evidence refused: {len(summary['evidence_refused'])} (summary.json "
                     "evidence_refused: forged or contested tokens, statuses)")
    refused = summary.get("implausible") or {}
    if any(refused.values()):
        lines.append(f"  refused as implausible (far beyond the model's scale): "
                     f"{refused.get('estimates', 0)} estimates, {refused.get('readings', 0)} "
                     "readings")
    if "mse_steady_after_recovery" in summary:
        after = summary.get("mse_steady_exact_after_recovery")
        gains = summary.get("after_recovery_gains")
        if gains:             # the window spans a change of gains for the same roles
            after = summary.get("mse_steady_exact_over_after_recovery_window")
        lines.append(f"  after recovery: mse_steady "
                     f"{steady_text(summary, 'mse_steady_after_recovery')}"
                     f" (predicted {after if after is not None else float('nan'):.4g}"
                     + (" over it: the gains of epoch " + ", then of epoch ".join(
                         f"{g['epoch']}" + (f" from step {g['from']}" if i else "")
                         for i, g in enumerate(gains)) if gains else "") + ")")
    return lines


def steady_text(summary: dict, key: str) -> str:
    """A steady MSE of a summary with its standard error and the steps it covers.

    >>> steady_text({"m": 0.2788, "m_se": 0.0123, "m_window": [300, 399]}, "m")
    '0.2788 ± 0.012 over steps 300-399'
    >>> steady_text({"m": 0.2788, "m_se": None, "m_window": [398, 399]}, "m")
    '0.2788 over steps 398-399 (too few for a standard error)'
    >>> steady_text({"m": 0.2788}, "m")
    '0.2788'
    """
    value, se, window = summary[key], summary.get(f"{key}_se"), summary.get(f"{key}_window")
    text = f"{value:.4g}"
    if se is not None:
        text += f" ± {se:.2g}"
    if window:
        text += f" over steps {window[0]}-{window[1]}"
        if se is None:
            text += " (too few for a standard error)"
    return text


#: Most warnings taken from the processes' logs into a summary (a log is never read whole
#: into the summary: the rest is counted).
MAX_LOG_WARNINGS = 20


def log_warnings(logs_dir) -> list:
    """The warnings the run's processes printed (``NAME: warning: TEXT`` lines of
    ``logs_dir/*.log``) as ``"LOG: TEXT"``, LOG the log's name, which says the process
    (``monitor-1.restart-1``: a monitor prints ``monitor 1: warning: ...`` in each of its
    lives), in file order, at most :data:`MAX_LOG_WARNINGS` (then one line saying how many
    more).

    >>> import pathlib, tempfile
    >>> d = pathlib.Path(tempfile.mkdtemp())
    >>> _ = (d / "world.log").write_text("world: started\\nworld: warning: float64 ran out\\n")
    >>> log_warnings(d)
    ['world: float64 ran out']
    """
    import re
    from pathlib import Path

    pattern = re.compile(r"^[\w.-]+(?: \d+)?: warning: (.*\S)")
    found, more = [], 0
    for path in sorted(Path(logs_dir).glob("*.log")):
        try:
            with open(path, errors="replace") as f:
                for line in f:
                    m = pattern.match(line)
                    if m is None:
                        continue
                    if len(found) < MAX_LOG_WARNINGS:
                        found.append(f"{path.stem}: {m.group(1)}")
                    else:
                        more += 1
        except OSError:
            continue
    if more:
        found.append(f"{more} more warnings in {logs_dir}")
    return found


def switch_steps(est_epoch_of_agent: dict, epoch: int, activate_at: int | None = None,
                 record_start: int | None = None):
    """The first step an agent computed under ``epoch``, from the epochs its estimates
    carried; None if it never did (it rejected that assignment, or ran a newer one first).

    An agent that takes a role without an estimate of its own (a standby) first publishes
    the estimate it starts from, stamped ``activate_at - 1`` under the new epoch: its
    switch is the step after. A record that begins (``record_start``) after the
    epoch's ``activate_at`` with the agent already under it from its beginning (a watch
    that joined later) shows no switch: it switched when told, ``activate_at``.

    >>> switch_steps({9: 0, 10: 1, 11: 1}, 1), switch_steps({9: 1, 10: 1}, 1)
    (10, 10)
    >>> switch_steps({9: 0, 10: 0}, 1) is None, switch_steps({9: 0, 10: 2}, 1) is None
    (True, True)
    >>> switch_steps({1018: 1, 1019: 1}, 1, activate_at=788, record_start=1018)
    788
    >>> switch_steps({820: 1, 821: 1}, 1, activate_at=788, record_start=0)   # late
    821
    """
    steps = sorted(k for k, e in est_epoch_of_agent.items() if e == epoch)
    if not steps:
        return None
    first = steps[0]
    if activate_at is not None and record_start is not None and activate_at <= first \
            and first == min(est_epoch_of_agent) and first <= record_start + 1:
        return activate_at
    return first if (first - 1) in est_epoch_of_agent else first + 1


def rosters_in_force(rosters, est_epoch, assigns):
    """The configurations that were really in force, read from what the agents published.

    ``rosters``: ``[(activate_at, ids, epoch)]`` heard from the monitor (the first the
    initial configuration); ``est_epoch``: agent -> {step: epoch of its estimate};
    ``assigns``: ``{(agent, epoch): assignment}`` heard. A roster was in force from the
    step at which the last of the agents it assigned a role switched to its epoch (at its
    ``activate_at`` when all went together). A roster that an assigned agent never ran
    (its ``activate_at`` passed before it heard it; a newer epoch came first) never was in
    force: the re-issue that follows is. A roster whose agents switched at different
    steps is kept from the last switch, and reported as mixed. An assigned agent that
    published nothing from the roster's step on while others did had stopped before it
    (a crash not yet convicted): the roster ran without it.

    Returns ``(in_force, mixed)``: ``[(step, ids, epoch)]`` and
    ``[{"epoch", "activate_at", "switched": {agent: step or None}}]`` for every roster
    that some of its agents ran and others did not, or ran from different steps (a roster
    none of them ran, rejected or superseded before its step, is simply not in force).

    >>> rosters = [(0, (1, 2, 3), 0), (175, (1, 2, 4), 1), (184, (1, 2, 4), 2)]
    >>> est = {a: {174: 0, 175: 1, 183: 1, 184: 2} for a in (1, 2)}
    >>> est[4] = {183: 2, 184: 2}      # rejected epoch 1 (too late), took epoch 2's role
    >>> assigns = {(a, e): {} for a in (1, 2, 4) for e in (1, 2)}
    >>> in_force, mixed = rosters_in_force(rosters, est, assigns)
    >>> in_force
    [(0, (1, 2, 3), 0), (184, (1, 2, 4), 2)]
    >>> mixed[0]["switched"]
    {1: 175, 2: 175, 4: None}
    >>> est = {1: {174: 0, 175: 1}, 2: {174: 0}, 4: {174: 0, 175: 1}}  # 2 stopped at 174
    >>> rosters_in_force(rosters[:2], est, assigns)
    ([(0, (1, 2, 3), 0), (175, (1, 2, 4), 1)], [])
    """
    out, mixed = [rosters[0]], []
    newest = {a: max(e) for a, e in est_epoch.items() if e}    # each agent's last step
    record_start = min((min(e) for e in est_epoch.values() if e), default=None)
    last = max(newest.values(), default=-1)
    newest_at: dict = {}
    for at, ids, epoch in rosters[1:]:
        newest_at[at] = max(newest_at.get(at, epoch), epoch)
    for at, ids, epoch in sorted(rosters[1:], key=lambda r: r[2]):
        if at > last:
            continue                       # after the run
        if newest_at[at] != epoch:
            # superseded at its own step by a newer epoch: never in force when every
            # agent that newer one was sent to ran it (an agent it was not sent to kept
            # the same role under this epoch's number); in force when the newer one came
            # too late for some, who ran this one instead
            newer = newest_at[at]
            told = [a for (a, e) in assigns if e == newer and newest.get(a, -1) >= at]
            if all(est_epoch.get(a, {}).get(at, newer) >= newer for a in told):
                continue
        assigned = sorted(a for (a, e) in assigns if e == epoch and a in ids) or list(ids)
        # an agent that published nothing from the roster's step on had stopped (a crash
        # the monitor had not convicted yet): the roster ran without it, as the simulator
        # replays a failed agent kept in an intermediate configuration
        if any(newest.get(b, -1) >= at for b in assigned):
            assigned = [a for a in assigned if a not in newest or newest[a] >= at]
        switched = {a: switch_steps(est_epoch.get(a, {}), epoch, at, record_start)
                    for a in assigned}
        if all(k is None for k in switched.values()):
            if any(est_epoch.get(a) for a in assigned):
                continue                   # nobody ran it: rejected, or superseded first
            out.append((at, tuple(ids), epoch))    # no estimate recorded: as sent
            continue
        if any(k != at for k in switched.values()):
            mixed.append({"epoch": epoch, "activate_at": at, "switched": switched})
        if any(k is None for k in switched.values()):
            continue
        out.append((max(switched.values()), tuple(ids), epoch))
    out = [out[0]] + sorted(out[1:], key=lambda r: (r[0], r[2]))
    return out, mixed


def configurations_run(rosters, est_epoch, assigns, kills, neighbours0):
    """Every configuration the agents ran, agent by agent: ``[(step, ids, {id: epoch})]``
    from each step at which some agent switched to a newer epoch, each agent running the
    role of the newest epoch it had switched to (read from the epochs its estimates
    carried). Where an epoch's agents switched together this is :func:`rosters_in_force`;
    where they did not (one heard its assignment after its ``activate_at`` and ran the
    older role until the re-issue), the steps between are a configuration of their own
    that the simulator replays like any other. ``ids`` are the newest epoch's, then the
    agents still running an older role, then the failed agents those roles still listen
    to. ``kills``: agent -> the step of its scripted crash; ``neighbours0``: agent -> the
    ids it listens to in the initial configuration.

    Each row ends with the ids that hold a role in it but had not started one (a standby
    that heard its assignment too late: it computes and publishes nothing until the
    re-issue it hears in time, and its receivers read only the failed agent's stream on
    its link, :class:`design.simulate.Recovery`'s ``waiting``).

    >>> rosters = [(0, (1, 2, 3), 0), (175, (1, 3), 1), (190, (1, 3), 2)]
    >>> est = {1: {174: 0, 175: 1, 189: 1, 190: 2}, 2: {160: 0},
    ...        3: {175: 0, 176: 0, 189: 0, 190: 2}}      # 3 heard epoch 1 too late
    >>> assigns = {(1, 1): {"neighbours": {3: 0.5}}, (3, 1): {"neighbours": {1: 0.5}},
    ...            (1, 2): {"neighbours": {3: 0.5}}, (3, 2): {"neighbours": {1: 0.5}}}
    >>> ring = {1: {2}, 2: {3}, 3: {2}}
    >>> for row in configurations_run(rosters, est, assigns, {2: 161}, ring): print(row)
    (175, (1, 3, 2), {1: 1, 3: 0, 2: 0}, ())
    (190, (1, 3), {1: 2, 3: 2}, ())
    >>> rosters = [(0, (1, 2, 3), 0), (175, (1, 4, 3), 1), (190, (1, 4, 3), 2)]
    >>> est = {1: {174: 0, 175: 1, 189: 1, 190: 2}, 2: {160: 0},
    ...        3: {174: 0, 175: 1, 189: 1, 190: 2},
    ...        4: {189: 2, 190: 2}}        # standby 4 heard epoch 1 too late
    >>> for row in configurations_run(rosters, est, assigns, {2: 161}, ring): print(row)
    (175, (1, 4, 3), {1: 1, 4: 1, 3: 1}, (4,))
    (190, (1, 4, 3), {1: 2, 4: 2, 3: 2}, ())
    """
    ids_of = {epoch: tuple(ids) for _, ids, epoch in rosters}

    def listens_to(agent, epoch):
        """The neighbours of ``agent`` in the role it ran under ``epoch``."""
        recorded = [e for (a, e) in assigns if a == agent and e <= epoch]
        if not recorded:
            return set(neighbours0.get(agent, ()))
        return {int(b) for b in assigns[(agent, max(recorded))].get("neighbours", {})}

    switches = {}                      # agent -> [(step, epoch)], steps increasing
    for a, by_step in est_epoch.items():
        found = sorted((0 if e == 0 else switch_steps(by_step, e), e)
                       for e in set(by_step.values()))
        switches[a] = [(k, e) for k, e in found if k is not None]
    steps = sorted({k for sw in switches.values() for k, _ in sw if k > 0})
    out = []
    for s in steps:
        running = {a: max((e for k, e in sw if k <= s), default=None)
                   for a, sw in switches.items()}
        running = {a: e for a, e in running.items() if e is not None}
        alive = [a for a in running if kills.get(a, math.inf) > s]
        newest = max((running[a] for a in alive), default=0)
        ids = list(ids_of.get(newest, ()))
        ids += [a for a in sorted(alive) if a not in ids]
        epochs = {a: running.get(a, newest) for a in ids}
        i = 0
        while i < len(ids):            # the failed agents the roles still listen to
            heard = listens_to(ids[i], epochs[ids[i]])
            for b in sorted(heard - set(ids)):
                ids.append(b)
                epochs[b] = running.get(b, epochs[ids[i]])
            i += 1
        waiting = tuple(a for a in ids if a not in running and kills.get(a, math.inf) > s)
        out.append((s, tuple(ids), epochs, waiting))
    return out


#: Configurations between the first and the last whose exact steady MSE a summary
#: computes (``rosters[i].mse_steady_exact``), for ``mse.png``: at most this many, and
#: only when the last configuration's took less than EXACT_IN_BETWEEN_S of CPU (a large
#: network's exact loop takes seconds to minutes).
MAX_ROSTERS_EXACT = 8
EXACT_IN_BETWEEN_S = 1.0


def residual_alerts(records) -> list:
    """The residual alerts of the monitors' records, one per alarm: the same alert (agent,
    fault, first alarm step) raised again by another monitor (one that took the seat and
    isolated the same statuses: it does not know what the one before it said) is counted
    once.

    >>> a = {"kind": "residual_alert", "agent": 1, "fault": "sensor bias", "step": 304,
    ...      "score": 1.03, "evidence": ["innovation of agent 1 at 1.03 x its threshold"]}
    >>> [r["agent"] for r in residual_alerts([a, dict(a, t=9.0), dict(a, step=700)])]
    [1, 1]
    """
    out, seen = [], set()
    for r in records:
        key = (r.get("agent"), r.get("fault"), r.get("step"))
        if r.get("kind") != "residual_alert" or key in seen:
            continue
        seen.add(key)
        out.append({"agent": r.get("agent"), "fault": r.get("fault"), "step": r.get("step"),
                    "score": r.get("score"), "evidence": r.get("evidence")})
    return out


def specs_in_force(rosters, assigns, scenario, G0, epoch=None):
    """``(ids, {id: RoleSpec})`` of the last roster (or of the one of ``epoch``), from the
    assignments recorded up to that epoch."""
    import numpy as np

    from design.roster import Roster, role_specs
    from design.roster import RoleSpec

    specs = role_specs(Roster.initial(scenario), G0)
    for (agent, e), m in sorted(assigns.items(), key=lambda kv: kv[0][1]):
        if epoch is not None and e > epoch:
            continue
        specs[agent] = RoleSpec(agent, tuple(m["measure"]), dict(m["neighbours"]),
                                float(m["self_weight"]), np.asarray(m["gain"]),
                                m.get("take_over"))
    if epoch is not None:
        return next(ids for _, ids, ep in rosters if ep == epoch), specs
    return rosters[-1][1], specs


def answered_by(agent: int, first: dict, reassigns: list, epoch_in_force) -> tuple:
    """``(reassignment, replacements)`` that answered the failure of ``agent`` as run.

    ``first`` is the monitor's first reassignment for it (an ``events.jsonl`` record). When
    its epoch never came into force (another failure was planned on top of it before its
    activation: ``epoch_in_force`` is later), the answer is the last reassignment up to
    that epoch, and each node ``first`` gave is followed to whoever measures it there
    (the agent it went to failed too and handed it on).

    >>> first = {"epoch": 1, "failed": [2], "replacements": [
    ...     {"failed": 2, "by": 1, "from": "c2a", "to": "c2b"}]}
    >>> later = {"epoch": 2, "failed": [1], "replacements": [
    ...     {"failed": 1, "by": 3, "from": "c1a", "to": "c1b"},
    ...     {"failed": 1, "by": 4, "from": "c2b", "to": "c2a"}]}
    >>> r, rep = answered_by(2, first, [first, later], 2)
    >>> r["epoch"], [(x["by"], x["to"]) for x in rep]
    (2, [(4, 'c2a')])
    >>> answered_by(2, first, [first, later], 1)[0]["epoch"]
    1
    """
    rep = [x for x in first.get("replacements", []) if x["failed"] == agent]
    if epoch_in_force is None or epoch_in_force <= first["epoch"]:
        return first, rep
    answer = first
    for later in sorted((r for r in reassigns
                         if first["epoch"] < r.get("epoch", -1) <= epoch_in_force),
                        key=lambda r: r["epoch"]):
        moved = {(x["failed"], x["from"]): x for x in later.get("replacements", [])}
        rep = [moved.get((x["by"], x["to"]), x) for x in rep]
        answer = later
    return answer, rep


#: Fewest steps of the after-recovery window under the final gains alone: enough for a
#: batch-means standard error (``2 * BATCHES``). A later change of gains for the same
#: roles (refined gains, gains for learned delays) that leaves fewer is measured over
#: the steps since those roles took effect instead (:func:`after_recovery_from`).
MIN_AFTER_STEPS = 2 * BATCHES


def after_recovery_from(steps_done, rosters) -> int:
    """The step from which ``mse_steady_after_recovery`` is measured (its window is the
    last quarter of the steps from there): the step the last configuration in force took
    effect; but when it only changed the gains of the roles before it and leaves a window
    of fewer than :data:`MIN_AFTER_STEPS` steps, the step those roles took effect.
    ``rosters``: ``[(activate_at, ids, epoch)]`` in force, more than one.

    Roles in force from step 224, refined gains from 346 in a run of 350 steps: the
    window was step 350 alone; it is now 319-350 (a quarter of 224-350).

    >>> rosters = [(0, (1, 2, 3), 0), (224, (1, 2, 4), 1), (346, (1, 2, 4), 2)]
    >>> after_recovery_from(range(351), rosters), after_recovery_from(range(700), rosters)
    (224, 346)
    """
    at = rosters[-1][0]
    if steady_window(sum(1 for k in steps_done if k >= at)) >= MIN_AFTER_STEPS:
        return at
    i = len(rosters) - 1
    while i > 1 and sorted(rosters[i - 1][1]) == sorted(rosters[-1][1]):
        i -= 1
    return rosters[i][0]


def _failures(events_path, rec, scenario, delays, steps_done, mse, G0):
    """``failures``, ``recovered``, MSE after recovery (live and exact) for the summary."""
    import json

    events, assigns = rec.events, rec.assigns
    rosters, mixed = rosters_in_force(rec.rosters, rec.est_epoch, assigns)
    records = []
    try:
        with open(events_path) as f:
            for line in f:
                try:
                    records.append(json.loads(line))
                except ValueError:
                    continue
    except (OSError, TypeError):        # no file (TypeError: no run folder)
        pass
    # a watcher has only those heard on the wire; a monitor whose disk filled wrote fewer
    if len(rec.monitor_events) > len(records):
        records = list(rec.monitor_events)
    deaths = {}
    for e in events:
        name = e.get("process", "")
        if name.startswith("agent-") and (e.get("exit_status") is not None or
                                          e.get("liveliness") is False or
                                          e.get("signal") == "SIGSTOP" or
                                          e.get("link") == "down"):
            deaths.setdefault(int(name.split("-")[1]), e)
    returns, dropped = {}, {}       # agent -> its SIGCONT / link up; its role dropped
    for e in events:
        name = e.get("process", "")
        if name.startswith("agent-") and (e.get("signal") == "SIGCONT" or e.get("link") == "up"):
            returns.setdefault(int(name.split("-")[1]), e)
        elif name.startswith("agent-") and e.get("role") == "dropped":
            dropped.setdefault(int(name.split("-")[1]), e)
    failures = []
    reassigns = [r for r in records if r.get("kind") == "reassign"]

    def of_agent(a, test):
        return [e for e in events if e.get("process") == f"agent-{a}" and test(e)]

    rejoined_at = [(r.get("agent"), r.get("t", math.inf)) for r in records
                   if r.get("kind") == "rejoin"]
    open_failure = {}       # agent -> (its failure entry, its verdict's time), until it rejoins
    for v in [r for r in records if r.get("kind") == "verdict"]:
        earlier, since = open_failure.get(v["agent"], (None, None))
        if earlier is not None and not any(
                a == v["agent"] and since <= t <= v.get("t", math.inf)
                for a, t in rejoined_at):
            # convicted again before it rejoined (a second monitor's verdict, or one
            # written again by a monitor that took the seat): the same failure
            earlier["verdicts"] = earlier.get("verdicts", 1) + 1
            continue
        entry = {"agent": v["agent"], "cause": v["cause"], "evidence": v["evidence"],
                 "detected_step": v["step"]}
        open_failure[v["agent"]] = (entry, v.get("t", -math.inf))
        # an agent convicted twice (it came back, rejoined, failed again): each verdict is
        # paired with the fault just before it and the reassignment just after it
        at = v.get("detected_t", v.get("t"))
        stops = of_agent(v["agent"], lambda e: e.get("signal") == "SIGSTOP"
                         or e.get("link") == "down")
        death = next((e for e in reversed(stops) if at is None or e.get("t", 0) <= at),
                     deaths.get(v["agent"]))
        if death is not None and (death.get("signal") == "SIGSTOP" or
                                  death.get("link") == "down"):
            entry["detection_ms"] = 1e3 * (at - death["t"])
        impaired = impairments_at(events, v["agent"], at, scenario, delays) \
            if at is not None else []
        if impaired:             # a link fault or `socmon inject` may explain the verdict
            entry["links_impaired"] = impaired
        since = death["t"] if death is not None else -math.inf
        back = next(iter(of_agent(v["agent"], lambda e: (e.get("signal") == "SIGCONT"
                                                        or e.get("link") == "up")
                                  and e.get("t", 0) >= since)), returns.get(v["agent"]))
        gone = next(iter(of_agent(v["agent"], lambda e: e.get("role") == "dropped"
                                  and e.get("t", 0) >= since)), dropped.get(v["agent"]))
        if back is not None and gone is not None and gone["t"] >= back["t"]:
            # resolution: the agent's status period (0.2 s)
            entry["fenced_ms"] = 1e3 * (gone["t"] - back["t"])
        r = next((r for r in reassigns if v["agent"] in r.get("failed", [])
                  and r.get("mono", math.inf) >= v.get("mono", -math.inf)), None)
        if r is not None:
            # the roles in force: this epoch's roster, or the re-issue that replaced it
            took = next(((at, ep) for at, _, ep in rosters[1:] if ep >= r["epoch"]), None)
            r, rep = answered_by(v["agent"], r, reassigns, took[1] if took else None)
            entry.update(epoch=took[1] if took else r["epoch"],
                         activate_at=took[0] if took else None,
                         activate_at_sent=r["activate_at"], precomputed=r.get("precomputed"),
                         gains=r.get("gains"))
            entry["replacement"] = ({"agent": rep[0]["by"], "node": rep[0]["to"]} if rep
                                    else None)
            if rep:
                # every node it measures now: a survivor keeps its own besides the new one
                role = rec.assigns.get((rep[0]["by"], r["epoch"])) or {}
                if role.get("measure"):
                    entry["replacement"]["measures"] = [str(x) for x in role["measure"]]
            entry["added_links"] = [{"from": int(a), "to": int(b)}
                                    for a, b in r.get("added_links", [])]
        failures.append(entry)
    absent = _no_monitor_windows(events)
    # a token that went and came back (a process paused past its lease, a link that
    # lapsed): the agent spoke again after it, by a status of a later step or its token
    spoke = {a: st.get("step", -1) for a, st in (getattr(rec, "status", None) or {}).items()}
    for a, e in list(deaths.items()):
        if e.get("liveliness") is not False or e.get("exit_status") is not None:
            continue
        # its last loss of the token not followed by a return: a standby paused past its
        # lease and killed later died at the second
        tokens = [x for x in events if x.get("process") == f"agent-{a}"
                  and x.get("liveliness") in (True, False)]
        last = tokens[-1] if tokens else e
        if last.get("liveliness") is True or spoke.get(a, -1) > last.get("step", -1):
            del deaths[a]
        else:
            deaths[a] = last
    failures += _undetected(deaths, {v["agent"] for v in records if v.get("kind") == "verdict"},
                            absent, rosters, steps_done[-1] if len(steps_done) else None)
    out = {"failures": failures, "rosters": [{"activate_at": at, "ids": list(ids),
                                               "epoch": ep} for at, ids, ep in rosters],
           "rosters_not_in_force": [{**m, "switched": {str(a): k for a, k
                                                        in m["switched"].items()}}
                                    for m in mixed],
           "reissues": [{"epoch": r.get("epoch"), "activate_at": r.get("activate_at"),
                         "reason": r.get("reason", "")}
                        for r in records if r.get("kind") == "reissue"],
           "evidence_refused": [{"reason": r.get("reason"), "agent": r.get("agent"),
                                 "detail": r.get("detail")}
                                for r in records if r.get("kind") == "evidence_refused"],
           "rejoins": [{"agent": r.get("agent"), "step": r.get("step"),
                        "healthy_s": r.get("healthy_s"), "standby": r.get("standby")}
                       for r in records if r.get("kind") == "rejoin"],
           "residual_alerts": residual_alerts(records)}
    for f in failures:           # a convicted agent that came back and passed probation
        back = [r for r in out["rejoins"] if r["agent"] == f["agent"]
                and (f.get("detected_step") or 0) <= (r["step"] or 0)]
        if back:
            f["rejoined_step"] = back[0]["step"]
    for m in mixed:
        out.setdefault("warnings", []).append(
            f"epoch {m['epoch']} (activate_at {m['activate_at']}) was not run by all its "
            "agents at that step: " + ", ".join(
                f"agent {a} {'from step ' + str(k) if k is not None else 'never'}"
                for a, k in sorted(m["switched"].items())))
    # configurations in force before the record began (a watch that joined later) whose
    # assignments it never heard: their roles, and so their predictions, are unknown
    before = [ep for at, _, ep in rosters[1:] if len(steps_done) and at <= steps_done[0]]
    roles_unheard = bool(before) and not any(0 < e <= max(before) for (_, e) in assigns)
    if len(rosters) > 1 and G0 is None:           # a watcher given no gains
        out["recovered"] = None
        out.setdefault("warnings", []).append("no gains given: recovery not evaluated")
    elif roles_unheard:
        out["recovered"] = None
        out["roles_unheard_before"] = int(steps_done[0])
        out.setdefault("warnings", []).append(
            f"epoch {max(before)} was in force before this record began (step "
            f"{steps_done[0]}) and its assignments were not heard: the roles in force and "
            "their exact predictions are unknown; recovery is not evaluated")
    elif len(rosters) > 1:
        at = rosters[-1][0]
        # the roles of the last roster in force: a later epoch's assignments (heard, but
        # due after the run's end) are not counted
        ids, specs = specs_in_force(rosters, assigns, scenario, G0, epoch=rosters[-1][2])
        recovered = all(a in specs for a in ids) and steps_done and steps_done[-1] >= at
        since = after_recovery_from(steps_done, rosters)
        after = [m for k, m in zip(steps_done, mse) if k >= since]
        out["mse_steady_after_recovery"] = steady_mse(after) if after else float("nan")
        after_window = [k for k in steps_done if k >= since][-steady_window(len(after)):] \
            if after else []
        out["mse_steady_after_recovery_se"] = batch_means_se(
            after[-steady_window(len(after)):]) if after else None
        out["mse_steady_after_recovery_window"] = [int(after_window[0]),
                                                   int(after_window[-1])] \
            if after_window else None
        exact_cost = None
        try:
            from design.closed_loop import exact_performance
            from design.roster import link_delay_table, roster_from_specs

            table = link_delay_table(scenario, delays)
            new, G, D = roster_from_specs(scenario, table, ids, specs)
            started = time.process_time()
            perf = exact_performance(new, G, D)
            exact_cost = time.process_time() - started
            out["rho_exact_after_recovery"] = perf.rho
            out["mse_steady_exact_after_recovery"] = perf.mse_or_inf
        except Exception as exc:       # noqa: BLE001 - reported, the run's data is kept
            out["mse_steady_exact_after_recovery"] = None
            out.setdefault("warnings", []).append(f"no exact prediction after recovery: {exc}")
        out["rosters"][-1]["mse_steady_exact"] = out["mse_steady_exact_after_recovery"]
        # the exact level of each configuration in force in between (mse.png draws it over
        # its steps), where the last one's was cheap; a churning run's many are left out
        cheap = exact_cost is not None and exact_cost < EXACT_IN_BETWEEN_S
        for r in out["rosters"][1:-1][:MAX_ROSTERS_EXACT if cheap else 0]:
            try:
                ids_r, specs_r = specs_in_force(rosters, assigns, scenario, G0,
                                                epoch=r["epoch"])
                r["mse_steady_exact"] = exact_performance(
                    *roster_from_specs(scenario, table, ids_r, specs_r)).mse_or_inf
            except Exception:          # noqa: BLE001 - a level not drawn, nothing else
                r["mse_steady_exact"] = None
        # a window that spans a change of gains: its prediction is the mean of the exact
        # levels of the gains in force over its steps
        spans = [(a, ep) for a, _, ep in rosters if after_window and a <= after_window[-1]]
        spans = [(max(a, after_window[0]), ep) for i, (a, ep) in enumerate(spans)
                 if i + 1 == len(spans) or spans[i + 1][0] > after_window[0]]
        if len(spans) > 1:
            levels = {r["epoch"]: r.get("mse_steady_exact") for r in out["rosters"]}
            gains = []
            for i, (a, ep) in enumerate(spans):
                if levels.get(ep) is None:
                    try:
                        levels[ep] = exact_performance(*roster_from_specs(
                            scenario, table, *specs_in_force(rosters, assigns, scenario, G0,
                                                             epoch=ep))).mse_or_inf
                    except Exception:  # noqa: BLE001 - no prediction over the window
                        levels[ep] = None
                end = spans[i + 1][0] if i + 1 < len(spans) else after_window[-1] + 1
                gains.append({"epoch": ep, "from": a, "steps": sum(
                    1 for k in after_window if a <= k < end), "mse_steady_exact": levels[ep]})
            out["after_recovery_gains"] = gains
            known = [g for g in gains if g["mse_steady_exact"] is not None]
            out["mse_steady_exact_over_after_recovery_window"] = float(sum(
                g["steps"] * g["mse_steady_exact"] for g in gains) / len(after_window)) \
                if len(known) == len(gains) else None
        # recovered: the roles in force, and the error after them near its exact level
        exact = out.get("mse_steady_exact_over_after_recovery_window")
        exact = out.get("mse_steady_exact_after_recovery") if exact is None else exact
        measured = out["mse_steady_after_recovery"]
        out["recovered"] = bool(recovered) and exact is not None and math.isfinite(exact) \
            and math.isfinite(measured) and measured <= RECOVERED_FACTOR * exact
        if recovered and not out["recovered"]:
            out.setdefault("warnings", []).append(
                f"not recovered: the roles are in force from step {at}, but the steady MSE "
                f"after them, {measured:.4g}, is not within {RECOVERED_FACTOR:g}x of their "
                f"exact prediction {exact if exact is not None else float('nan'):.4g}")
    elif any(f["agent"] in rosters[-1][1] for f in failures):
        out["recovered"] = False          # an agent with a role failed, and no roles moved
    for a, b in absent:
        out.setdefault("warnings", []).append(
            f"NO MONITOR ALIVE from step {a} " + ("to the end of the run" if b == math.inf
                                                  else f"to step {b}")
            + ": a failure in that window was neither detected nor recovered")
    out["no_monitor"] = [{"from": a, "to": None if b == math.inf else b} for a, b in absent]
    unanswered = sorted({f["agent"] for f in failures if f.get("detected") is not False
                         and f.get("rejoined_step") is None
                         and f["agent"] in rosters[-1][1]})
    if unanswered:
        out["recovered"] = False
        out.setdefault("warnings", []).extend(
            f"agent {a} was convicted but the roles answering it were not in force by the "
            "run's end: not recovered" for a in unanswered)
    if any(f.get("detected") is False and f.get("role") == "active" for f in failures):
        out["recovered"] = False
        out.setdefault("warnings", []).extend(
            f"agent {f['agent']} died at step {f['died_step']} and was never convicted "
            f"({f['why']}): its role was not recovered" for f in failures
            if f.get("detected") is False and f.get("role") == "active")
    return out


def _no_monitor_windows(events) -> list:
    """``(from, to)`` steps while no monitor token was up (the recorder's monitor events);
    ``to`` is inf when none came back. Before the clock (step -1) no step runs and no
    failure can go unanswered (the world starts its clock once the first monitor is up):
    a window that ended there (or as the clock started) is none, one that went on starts at
    step 0 (a standby
    monitor's token that lapsed on a loaded host before the clock was reported as "NO
    MONITOR ALIVE from step -1 to step -1").

    >>> _no_monitor_windows([{"process": "monitor", "monitors_alive": 0, "step": -1},
    ...                      {"process": "monitor", "monitors_alive": 1, "step": 0},
    ...                      {"process": "monitor", "monitors_alive": 0, "step": 10},
    ...                      {"process": "monitor", "monitors_alive": 1, "step": 30},
    ...                      {"process": "monitor", "monitors_alive": 0, "step": 50}])
    [(10, 30), (50, inf)]
    """
    absent, since = [], None
    for e in events:
        if e.get("process") == "monitor" and "monitors_alive" in e:
            if e["monitors_alive"] == 0:
                since = e.get("step", -1)
            elif since is not None:
                absent.append((since, e.get("step", since)))
                since = None
    if since is not None:
        absent.append((since, math.inf))
    return [(max(a, 0), b) for a, b in absent if b > 0 or (a >= 0 and b >= 0)]


def _undetected(deaths, convicted, absent, rosters, last_step=None) -> list:
    """Failures entries for the agents whose process went (exit or liveliness token gone)
    and that no verdict named: ``detected: False``, the step it died, whether it held a
    role then (``role``: the roster in force at that step) and ``why``: ``"no monitor
    alive"`` when it died in one of the ``absent`` windows, else ``"no verdict"``. An
    exit at the run's last step (``last_step``) is the end of the run, not a failure."""
    out = []
    for agent, e in sorted(deaths.items()):
        if agent in convicted or (e.get("exit_status") is None and e.get("liveliness") is not False):
            continue           # a stop or a link down that no verdict followed: it came back
        k = e.get("step", -1)
        if last_step is not None and k >= last_step:
            continue
        ids = next((ids for at, ids, _ in reversed(rosters) if at <= k), rosters[0][1])
        out.append({"agent": agent, "cause": "crash", "detected": False,
                    "evidence": ("exit status " + str(e["exit_status"])
                                 if e.get("exit_status") is not None else "liveliness token gone"),
                    "died_step": k, "detected_step": None,
                    "role": "active" if agent in ids else "standby",
                    "why": "no monitor alive" if any(a <= k <= b for a, b in absent)
                    else "no verdict"})
    return out


def was_compared(how: str) -> bool:
    """Whether :func:`compare_simulator` compared estimates (its ``what was compared``),
    rather than saying why the run could not be replayed (its difference then infinite).

    >>> was_compared("estimates (201 compared)"), was_compared("incomplete run")
    (True, False)
    """
    return how.startswith("estimates")


def links_impaired(events, scenario, delays) -> list:
    """``(step, agent)`` of each impairment the recorder heard on the links into an agent
    (its status's ``links`` other than the run's own delays), in order: a link fault of the
    run, or one ``socmon inject`` (or anyone with the operator key) set during it. The
    simulator replays none of them.

    >>> from design.scenario import load_scenario
    >>> s = load_scenario("paper-14-live")
    >>> links_impaired([{"process": "agent-2", "links": {}, "step": -1},
    ...                 {"process": "agent-2", "links": {"1": {"drop": 0.5}}, "step": 120}],
    ...                s, np.zeros((3, 3), dtype=int))
    [(120, 2)]
    """
    from design.roster import link_delay_table

    table = link_delay_table(scenario, delays)
    out = []
    for e in events:
        process = e.get("process", "")
        if "links" not in e or not process.startswith("agent-"):
            continue
        a = int(process.removeprefix("agent-"))
        if e["links"] != _run_links(table, a):
            out.append((e.get("step"), a))
    return out


def _run_links(table, a) -> dict:
    """The links into agent ``a`` as its status shows them with only the run's own delays."""
    return {str(b + 1): {"delay_steps": int(d)} for b, d in enumerate(table[a - 1])
            if b != a - 1 and d > 0}


def impairments_at(events, agent: int, t: float, scenario, delays) -> list:
    """The impairments in force at time ``t`` on the links into and out of ``agent`` other
    than the run's own delays, as the receivers' statuses last showed them before ``t``
    (each ``"SRC->DST what"``; ``0`` is the world's link, its sensor readings): what a
    conviction of ``agent`` may owe to a link fault or ``socmon inject`` rather than to
    the agent itself.

    >>> from design.scenario import load_scenario
    >>> s, d = load_scenario("paper-14-live"), np.zeros((3, 3), dtype=int)
    >>> ev = [{"process": "agent-1", "links": {"2": {"partition": True}}, "t": 5.0},
    ...       {"process": "agent-2", "links": {"3": {"drop": 0.5, "burst": 5.0}}, "t": 6.0},
    ...       {"process": "agent-1", "links": {}, "t": 9.0}]
    >>> impairments_at(ev, 2, 7.0, s, d)
    ['2->1 cut', '3->2 drop 0.5']
    >>> impairments_at(ev, 2, 9.5, s, d)
    ['3->2 drop 0.5']
    >>> impairments_at(ev, 2, 4.0, s, d)
    []
    """
    from design.roster import link_delay_table

    table = link_delay_table(scenario, delays)
    last = {}
    for e in events:
        process = e.get("process", "")
        if "links" in e and process.startswith("agent-") and e.get("t", math.inf) <= t:
            last[int(process.removeprefix("agent-"))] = e["links"]
    out = []
    for dst, links in sorted(last.items()):
        own = _run_links(table, dst) if dst <= len(table) else {}
        for src, params in sorted(links.items(), key=lambda kv: int(kv[0])):
            if (int(src) == agent or dst == agent) and own.get(src) != params:
                out.append(f"{src}->{dst} {_impairment_words(params)}")
    return out


def _impairment_words(params: dict) -> str:
    """``{"partition": True}`` -> ``"cut"``; ``{"drop": 0.5}`` -> ``"drop 0.5"``; ..."""
    words = []
    if params.get("partition"):
        words.append("cut")
    if params.get("drop"):
        words.append(f"drop {params['drop']:g}")
    if params.get("delay_steps"):
        words.append(f"delay {params['delay_steps']} steps")
    if params.get("delay_ms"):
        words.append(f"delay {params['delay_ms']:g} ms"
                     + (f" ± {params['jitter_ms']:g}" if params.get("jitter_ms") else ""))
    return ", ".join(words) or "changed"


def compare_simulator(config, rec, steps_done):
    """Largest difference to ``design.simulate`` (trial 0, same seed, delays and drops).

    ``max_k max_a |xhat_live - xhat_sim| / max(1, |x_k|)`` (infinity norms) over every
    estimate both computed. With scripted crashes at one step (``--kill``) and the
    monitor's reassignments, the simulator replays every crash at its step (any number,
    at different steps; a standby killed before it took a role computed nothing) and the
    chain of configurations in force (:func:`rosters_in_force`: the step the agents
    switched, the roles and gains of their assignments; where they did not switch
    together, :func:`configurations_run`, agent by agent).
    Returns ``(difference, what was compared)``; ``(inf, why not)`` when the run cannot be
    replayed (:func:`was_compared` tells them apart).
    """
    from design.roster import link_delay_table, roster_from_specs
    from design.simulate import Recovery, simulate

    c = config
    G, K = c.G, c.steps
    fail = recover = None
    # a crash scheduled after the run's last step never happened
    kills = {f.agent: f.step for f in c.faults if f.kind == "crash" and f.step <= K}
    # what an agent was scripted to do wrong (a lie, a sensor fault) the simulator does
    # alike, a standby's once it holds a role
    from design.simulate import FAULT_KINDS as SIMULATED
    from design.simulate import Fault as SimFault

    from agent.run.fault_kinds import REPLAYED_FAULTS, REPLAYED_WORDS

    scripted = [f for f in c.faults if f.kind in SIMULATED]
    not_replayed = sorted({f.kind for f in c.faults if f.kind not in REPLAYED_FAULTS})
    if not_replayed:       # up refuses them with --check-simulator: a run of its own API
        return float("inf"), (f"the simulator replays {REPLAYED_WORDS} only, not "
                              f"{', '.join(not_replayed)}")
    sim_faults = [SimFault(f.kind, f.agent - 1, f.step, f.value) for f in scripted]
    if kills:
        # a standby killed before it took a role never computed: nothing to replay
        steps_of = sorted({f for a, f in kills.items() if a <= c.scenario.N})
        fail = [(f, sorted(a - 1 for a, g in kills.items() if g == f and a <= c.scenario.N))
                for f in steps_of] or None
        rosters, mixed = rosters_in_force(rec.rosters, rec.est_epoch, rec.assigns)
        if mixed:
            W0 = c.scenario.W
            neighbours0 = {i + 1: {j + 1 for j in range(c.scenario.N) if j != i and W0[i, j] > 0}
                           for i in range(c.scenario.N)}
            phases = configurations_run(rec.rosters, rec.est_epoch, rec.assigns, kills,
                                        neighbours0)
        else:
            phases = [(at, ids, {a: epoch for a in ids}, ()) for at, ids, epoch in rosters[1:]]
        at_end, ids_end, epoch_end = rosters[-1]
        dead_at_end = sorted(a for a in ids_end if kills.get(a, math.inf) <= at_end)
        if len(rosters) > 1 and dead_at_end:
            return float("inf"), (
                f"agent {dead_at_end[0]} was killed before the configuration in force at the "
                f"run's end (epoch {epoch_end}) and not yet replaced: the simulator's last "
                "configuration holds no failed agent")
        took = sorted(a for a in kills if a > c.scenario.N
                      and any(a in ids for _, ids, _, _ in phases))
        if took:
            return float("inf"), (
                f"agent {took[0]} was killed after it took a role: the simulator fails "
                "agents of the initial configuration only")
        table = link_delay_table(c.scenario, c.delays)
        specs_of: dict = {}           # epoch -> {id: RoleSpec} as of that epoch
        chain, before = [], set(rosters[0][1])
        for at, ids, epochs, waiting in phases:
            for e in set(epochs.values()) - set(specs_of):
                specs_of[e] = specs_in_force(rec.rosters, rec.assigns, c.scenario, G,
                                             epoch=e)[1]
            specs = {a: specs_of[epochs[a]][a] for a in ids}
            new, G_new, D_new = roster_from_specs(c.scenario, table, ids, specs,
                                                  transient=len(set(epochs.values())) > 1)
            # a standby takes over when it starts its role (not while it waits for it)
            replaces = {a: specs[a].take_over - 1 for a in ids
                        if a not in before and specs[a].take_over is not None}
            chain.append(Recovery(new, G_new, tuple(ids), replaces=replaces, delays=D_new,
                                  activate_at=at, waiting=frozenset(waiting)))
            before = set(ids) - set(waiting)
        recover = chain or None
        if recover is not None and fail is None:
            return float("inf"), ("a reassignment after the kill of a standby only cannot "
                                  "be replayed")
    elif len(rec.rosters) > 1:
        return float("inf"), "a reassignment without a scripted crash cannot be replayed"
    res = simulate(c.scenario, G, steps=K, trials=1, seed=c.seed, delays=c.delays,
                   drop=c.drop, fail=fail, recover=recover, coordinates="absolute",
                   record_estimates=True, faults=sim_faults)
    from agent.run.recorder import kept_step

    every = c.record_every
    if not len(steps_done) or steps_done[-1] < K:
        return float("inf"), "incomplete run"
    # steps the processes ran and the recorder missed (record_gaps) are not compared
    missing = sum(kept_step(k, every, K) for k in range(K + 1)) - len(steps_done)
    sim_est = np.asarray(res.estimates)[0]
    # the simulator records a liar's own (honest) estimate, the recorder what it published
    lies = {f.agent + 1: f for f in sim_faults if f.kind == "lie"}
    sigma = math.sqrt(c.scenario.measurement_noise)
    worst, compared, first = 0.0, 0, None
    for k in steps_done:
        scale = max(1.0, float(np.abs(rec.truth[k]).max()))
        for col, a in enumerate(res.estimate_ids):
            if k in rec.est.get(a, {}) and np.isfinite(sim_est[k, col]).all():
                lie = lies.get(a)
                sim = sim_est[k, col] if lie is None else \
                    sim_est[k, col] + lie.offset(k, sigma) * lie.vector(c.scenario.n)
                d = float(np.abs(rec.est[a][k] - sim).max()) / scale
                worst = max(worst, d)
                compared += 1
                if first is None and not d <= CHECK_TOL:
                    first = (k, a)
    where = "" if first is None else (f"; the first above {CHECK_TOL:g}: agent {first[1]} "
                                      f"at step {first[0]}")
    unrecorded = f"; {missing} steps not recorded" if missing else ""
    return worst, f"estimates ({compared} compared{unrecorded}{where})"


def _write(path, data, written=None) -> None:
    """:func:`agent.run.folder.write_atomic`; a failure raised as
    :class:`agent.run.folder.RunFolderError`, ``written`` (names) appended to on success."""
    from agent.run.folder import RunFolderError, write_atomic

    try:
        write_atomic(path, data)
    except RunFolderError:
        raise
    except OSError as exc:
        raise RunFolderError(path, exc, written or []) from None
    if written is not None:
        written.append(Path(path).name)


def save_estimates(path, steps_done, truth, est, agents, n, written=None):
    """truth (K+1, n) and estimates (K+1, agents, n), NaN where nothing was received;
    written atomically (:class:`agent.run.folder.RunFolderError` if it cannot be)."""
    import numpy as np

    X = np.full((len(steps_done), n), np.nan)
    E = np.full((len(steps_done), len(agents), n), np.nan)
    for r, k in enumerate(steps_done):
        X[r] = truth[k]
        for c, a in enumerate(agents):
            if k in est[a]:
                E[r, c] = est[a][k]
    buf = io.BytesIO()
    np.savez(buf, step=np.array(steps_done, dtype=int), truth=X, estimates=E,
             agents=np.array(agents, dtype=int))
    _write(path, buf.getvalue(), written)


def pyplot():
    """matplotlib's pyplot on the Agg backend, or None when matplotlib is missing."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    return plt


def plottable(mse) -> np.ndarray:
    """Mask of the MSE values a log plot can show (finite, positive, not overflowing)."""
    mse = np.asarray(mse, dtype=float)
    return np.isfinite(mse) & (mse > 0) & (mse < 1e250)


def smoothing_window(steps: int) -> int:
    """Steps of the running mean ``mse.png`` draws over the raw trace: a 50th of the run,
    at least 5; 1 (no smoothing) for runs under 100 steps.

    >>> [smoothing_window(k) for k in (50, 400, 4000)]
    [1, 8, 80]
    """
    return 1 if steps < 100 else max(5, steps // 50)


def running_mean(values, window: int) -> np.ndarray:
    """The mean of each ``window`` consecutive values ending at each one (fewer at the
    start), values a log plot cannot show (not finite, not positive) left out; NaN where
    none is left.

    >>> running_mean([1.0, 3.0, float("nan"), 5.0], 2).tolist()
    [1.0, 2.0, 3.0, 5.0]
    """
    v = np.asarray(values, dtype=float)
    ok = plottable(v)
    total = np.concatenate([[0.0], np.cumsum(np.where(ok, v, 0.0))])
    count = np.concatenate([[0], np.cumsum(ok)])
    hi = np.arange(1, len(v) + 1)
    lo = np.maximum(0, hi - int(window))
    n = count[hi] - count[lo]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, (total[hi] - total[lo]) / np.maximum(n, 1), np.nan)


#: characters of ``mse.png``'s title that fit over its axes (9.5 in wide figure, the
#: legend beside the axes, 10 pt: about 7 px a character on about 560 px); a title is
#: centred over the axes, so a longer one starts left of the figure and is cut off
TITLE_CHARS = 80


def id_ranges(ids) -> str:
    """Agent ids, sorted, runs of consecutive ids as ranges.

    >>> id_ranges([6, 1, 2, 3, 4, 8, 9, 10, 11, 12])
    '1-4, 6, 8-12'
    >>> id_ranges([4, 2])
    '2, 4'
    """
    runs = []
    for a in sorted(set(ids)):
        if runs and a == runs[-1][1] + 1:
            runs[-1][1] = a
        else:
            runs.append([a, a])
    return ", ".join(f"{lo}" if lo == hi else f"{lo}-{hi}" if hi > lo + 1 else f"{lo}, {hi}"
                     for lo, hi in runs)


def roster_words(ids, first=None) -> str:
    """Agents ``ids`` in few words: the first roster as a count ("16 agents", when they
    are 1 to N) or ranges; a later one against the ``first`` ("all but 5", "all but 1,
    plus 4") or as ranges, whichever is shorter.

    >>> roster_words(range(1, 17)), roster_words([1, 2, 4])
    ('16 agents', 'agents 1, 2, 4')
    >>> roster_words([1, 2, 3, 4, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16], range(1, 17))
    'all but 5'
    >>> roster_words([4, 2, 3], [1, 2, 3])
    '2-4'
    """
    ids = sorted(set(ids))
    if first is None:
        return (f"{len(ids)} agents" if ids == list(range(1, len(ids) + 1))
                else f"agents {id_ranges(ids)}")
    first = sorted(set(first))
    gone, new = [a for a in first if a not in ids], [a for a in ids if a not in first]
    but = (f"all but {id_ranges(gone)}" if gone else "all") + (f", plus {id_ranges(new)}"
                                                                if new else "")
    return min((but, id_ranges(ids)), key=len)      # a tie: "all but"


def plot_title(summary) -> str:
    """``mse.png``'s title: the scenario, the seed, the agents at the start and, after
    the failures, from the step the last roles took effect (a change of gains for the
    same roles is no reassignment: the figure marks it). At most :data:`TITLE_CHARS`
    characters beside the scenario's name, whatever the number of agents.

    >>> plot_title({"scenario": "p", "seed": 0, "rosters": [{"activate_at": 0, "ids": [1, 2]},
    ...             {"activate_at": 173, "ids": [4, 2]}]})
    'p, seed 0: 2 agents; from step 173: 2, 4 (1 reassignment)'
    >>> plot_title({"scenario": "c", "seed": 0, "rosters": [
    ...     {"activate_at": 0, "ids": list(range(1, 17))},
    ...     {"activate_at": 161, "ids": [a for a in range(1, 17) if a != 5]},
    ...     {"activate_at": 184, "ids": [a for a in range(1, 17) if a != 5]}]})
    'c, seed 0: 16 agents; from step 161: all but 5 (1 reassignment)'
    """
    rosters = summary.get("rosters") or []
    head = f"{summary['scenario']}, seed {summary['seed']}: "
    if not rosters:
        return head + f"{summary.get('agents')} agents"
    first, last = rosters[0]["ids"], rosters[-1]["ids"]
    changes = [i for i in range(1, len(rosters))
               if sorted(rosters[i]["ids"]) != sorted(rosters[i - 1]["ids"])]
    if not changes:
        return head + roster_words(first)
    n = len(changes)
    tail = f" ({n} reassignment{'s' if n > 1 else ''})"
    since = f"; from step {rosters[changes[-1]]['activate_at']}: "
    title = head + roster_words(first) + since + roster_words(last, first) + tail
    if len(title) - len(summary["scenario"]) > TITLE_CHARS:        # ids too scattered
        title = head + f"{len(set(first))} agents" + since + f"{len(set(last))} agents" + tail
    return title


def gain_changes(summary) -> list:
    """Steps at which a configuration took effect that no failure explains (new gains for
    the same roles: a refined gain, gains for learned delays), as ``mse.png`` marks them
    (the first was once drawn unlabelled when a failure's came before it).

    >>> gain_changes({"rosters": [{"activate_at": 0}, {"activate_at": 174},
    ...                           {"activate_at": 307}],
    ...               "failures": [{"activate_at": 174}]})
    [307]
    """
    failed_at = {f.get("activate_at") for f in summary.get("failures", [])}
    return [r["activate_at"] for r in summary.get("rosters", [])[1:]
            if r.get("activate_at") not in failed_at]


def _clusters(items, near: int) -> list:
    """``(step, ...)`` tuples in groups of steps within ``near`` of the group's first, in
    order of step."""
    groups = []
    for item in sorted(items, key=lambda it: it[0]):
        if groups and item[0] - groups[-1][0][0] <= near:
            groups[-1].append(item)
        else:
            groups.append([item])
    return groups


def _grouped(pairs) -> dict:
    """``{key: [values]}`` of ``(key, value)`` pairs, keys in their first order."""
    out = {}
    for key, value in pairs:
        out.setdefault(key, []).append(value)
    return out


def event_labels(summary, near: int = 0) -> dict:
    """The words ``mse.png`` writes beside its event lines: ``{"faults": ..., "detected":
    ..., "reassigned": ...}``, each a list of ``(first step, last step, text)``. Events of
    one kind within ``near`` steps of one another share one label: two labels at one
    step printed over one another ("crash 3" on "crash 11" read "crash 31").

    >>> failures = [{"agent": a, "cause": "crash", "detected_step": 201, "activate_at": 210,
    ...              "replacement": {"agent": r}} for a, r in ((3, 2), (11, 1))]
    >>> faults = [{"step": 200, "kind": "crash", "agent": a} for a in (3, 11)]
    >>> for kind, labels in event_labels({"faults": faults, "failures": failures}).items():
    ...     print(kind, labels)
    faults [(200, 200, 'crash 3, 11')]
    detected [(201, 201, 'agents 3, 11: crash')]
    reassigned [(210, 210, 'agent 2 for 3, agent 1 for 11')]
    """
    def label(groups, words):
        return [(g[0][0], g[-1][0], words(g)) for g in groups]

    def agents(ids):
        return f"agent{'s' if len(ids) > 1 else ''} {', '.join(map(str, ids))}"

    faults = [(f["step"], f.get("kind", "fault"), f.get("agent"))
              for f in summary.get("faults", [])]
    failures = [f for f in summary.get("failures", []) if f.get("detected") is not False]
    detected = [(f["detected_step"], f["cause"], f["agent"]) for f in failures]
    reassigned = [(f["activate_at"], (f.get("replacement") or {}).get("agent"), f["agent"])
                  for f in failures if f.get("activate_at") is not None
                  and (f.get("replacement") or {}).get("agent") is not None]
    return {
        "faults": label(_clusters(faults, near), lambda g: "; ".join(
            kind + "".join(f"{', ' if i else ' '}{a}" for i, a in enumerate(filter(None, ids)))
            for kind, ids in _grouped((kind, a) for _, kind, a in g).items())),
        "detected": label(_clusters(detected, near), lambda g: "; ".join(
            f"{agents(ids)}: {cause}" for cause, ids in
            _grouped((cause, a) for _, cause, a in g).items())),
        "reassigned": label(_clusters(reassigned, near), lambda g: ", ".join(
            f"agent {rep} for {a}" for _, rep, a in g)),
    }


def write_run_folder(out, summary, steps_done, mse, predicted, recording=None, n=None):
    """The run folder's summary, MSE per step, ``mse.png`` and, of ``recording`` (with
    ``n`` states), the assignments heard and ``estimates.npz``: every run's folder (``up``,
    ``watch --out``, ``chaos``) holds the same files. Every file is written atomically
    (:func:`agent.run.folder.write_atomic`), the summary first.
    Returns the names written; a file that cannot be written (a full disk) raises
    :class:`agent.run.folder.RunFolderError` naming it and those written whole before it."""
    import json
    import sys

    from agent.run.jsonable import to_jsonable

    written = []
    _write(out / "summary.json", json.dumps(to_jsonable(summary), indent=2) + "\n", written)
    _write(out / "mse.csv", "step,mse\r\n" + "".join(
        f"{k},{float(m)!r}\r\n" for k, m in zip(steps_done, mse)), written)
    _write(out / "mse.json", json.dumps(to_jsonable(
        {"step": steps_done, "mse": list(mse)})) + "\n", written)
    if recording is not None:
        _write(out / "assignments.json", json.dumps(to_jsonable(
            [{"agent": a, "epoch": e, **m} for (a, e), m in sorted(recording.assigns.items())]))
            + "\n", written)
        agents = [a for a in sorted(recording.est) if recording.est[a]]
        save_estimates(out / "estimates.npz", steps_done, recording.truth, recording.est,
                       agents, n, written)
    plt = pyplot()
    if plt is None:
        return written
    ok = plottable(mse)
    mse = np.asarray(mse, dtype=float)
    steps_done = np.asarray(steps_done)
    fig, ax = plt.subplots(figsize=(9.5, 4.2))
    window = smoothing_window(len(mse))
    every = summary.get("record_every", 1)
    each = "each step" if every == 1 else f"every {every}th step"
    if window > 1:       # a long run's raw trace is a solid block: its running mean on top
        ax.semilogy(steps_done[ok], mse[ok], lw=0.6, color="tab:blue", alpha=0.3,
                    label=f"live run, {each}")
        ax.semilogy(steps_done, running_mean(mse, window), lw=1.4, color="tab:blue",
                    label=f"live run, mean of {window} {'steps' if every == 1 else 'of them'}")
    else:
        ax.semilogy(steps_done[ok], mse[ok], lw=1,
                    label="live run" + ("" if every == 1 else f", {each}"))
    # the exact level of each configuration over the steps it was in force
    rosters = summary.get("rosters") or []
    first_switch = rosters[1]["activate_at"] if len(rosters) > 1 else None
    last_step = int(steps_done[-1]) if len(steps_done) else 0
    if predicted and predicted != float("inf"):
        ax.hlines(predicted, 0, first_switch if first_switch is not None else last_step,
                  color="k", ls="--", lw=0.9, label="exact steady MSE, initial configuration")
    for i, r in enumerate(rosters[1:], start=1):
        level = r.get("mse_steady_exact")
        if i == len(rosters) - 1 and level is None:
            level = summary.get("mse_steady_exact_after_recovery")
        if level and level != float("inf"):
            end = rosters[i + 1]["activate_at"] if i + 1 < len(rosters) else last_step
            ax.hlines(level, r["activate_at"], end, color="tab:green", ls="--", lw=0.9,
                      label="exact steady MSE of the configuration in force"
                      if i == 1 else None)
    top = ax.get_xaxis_transform()          # x in steps, y in axes fraction: labels on top
    detected = reassigned = False
    for f in summary.get("failures", []):
        if f.get("detected") is False:
            ax.axvline(f["died_step"], color="tab:red", lw=1.5, ls=":",
                       label=f"agent {f['agent']} died, never convicted ({f['why']})")
            continue
        ax.axvline(f["detected_step"], color="tab:red", lw=0.8, ls="--",
                   label=None if detected else "detected")
        detected = True
        if f.get("activate_at") is not None:
            ax.axvline(f["activate_at"], color="tab:green", lw=0.8,
                       label=None if reassigned else "reassigned")
            reassigned = True
    for i, f in enumerate(summary.get("faults", [])):
        ax.axvline(f["step"], color="k", lw=0.7, alpha=0.7,
                   label="fault scheduled" if i == 0 else None)
    # a label a text line high (7 pt) apart at the least: nearer events share one
    labels = event_labels(summary, near=last_step // 50)
    for first, _, text in labels["detected"]:
        ax.text(first, 0.99, f" {text}", transform=top,
                rotation=90, va="top", ha="right", fontsize=7, color="tab:red")
    for _, last, text in labels["reassigned"]:
        ax.text(last, 0.01, f" {text}", transform=top,
                rotation=90, va="bottom", ha="left", fontsize=7, color="tab:green")
    for first, _, text in labels["faults"]:
        ax.text(first, 0.01, f"{text} ", transform=top,
                rotation=90, va="bottom", ha="right", fontsize=7, color="0.25")
    labelled = set()        # one legend entry per reason given by the monitor
    for r in summary.get("reissues", []):
        if isinstance(r.get("activate_at"), int):
            reason = str(r.get("reason") or "activate_at had passed")[:60]
            ax.axvline(r["activate_at"], color="tab:orange", lw=0.8, ls="-.",
                       label=None if reason in labelled else f"roles re-issued: {reason}")
            labelled.add(reason)
    for i, k in enumerate(gain_changes(summary)):
        ax.axvline(k, color="tab:cyan", lw=0.9, ls="-.",
                   label="new gains in force (same roles)" if i == 0 else None)
    if summary.get("diverged_at") is not None:
        ax.axvline(summary["diverged_at"], color="tab:red", lw=1.5,
                   label="DIVERGED")
    changed = sorted({e["step"] for e in summary.get("events", [])
                      if "links" in e and isinstance(e.get("step"), int) and e["step"] >= 0})
    for i, k in enumerate(changed):
        ax.axvline(k, color="tab:purple", lw=0.6, ls=":",
                   label="link impairments changed" if i == 0 else None)
    ax.set_xlabel("step")
    ax.set_ylabel("MSE (mean over agents and states)")
    ax.set_title(plot_title(summary), fontsize=10)
    # beside the axes: inside, it hid the fault and recovery lines of some runs
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0,
              fontsize="small")
    png = io.BytesIO()
    try:
        fig.tight_layout()
        fig.savefig(png, format="png", dpi=110)
    except (OverflowError, ValueError) as exc:  # e.g. a diverged run's huge values
        print(f"up: warning: no mse.png ({type(exc).__name__}: {exc})", file=sys.stderr)
        png = None
    finally:
        plt.close(fig)
    if png is not None:
        _write(out / "mse.png", png.getvalue(), written)
    return written
